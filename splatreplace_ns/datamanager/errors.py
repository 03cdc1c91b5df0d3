"""The error every dataset check raises."""

from __future__ import annotations

from typing import List, Union


class DatasetFormatError(ValueError):
    """A dataset file is missing or malformed: one line per problem, each naming the file and the field.

    Args:
        problems: one message, or every problem found (``problems`` keeps them; the message joins them by lines).
    """

    def __init__(self, problems: Union[str, List[str]]) -> None:
        self.problems = [problems] if isinstance(problems, str) else list(problems)
        super().__init__("\n".join(self.problems))
