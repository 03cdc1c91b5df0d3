"""The error every dataset check raises."""


class DatasetFormatError(ValueError):
    """A dataset file is missing or malformed; the message names the file and the problem."""
