"""The errors that name a bad input (a dataset file, a click, an ONNX model): a user sees their one-line message,
not a traceback, from ``splatreplace`` and from ``ns-train splat-replace`` alike."""

from __future__ import annotations

import sys


def user_error_types() -> tuple:
    """The exception classes whose message is the whole story."""
    from splatreplace_ns.datamanager.errors import DatasetFormatError
    from splatreplace_ns.instances.projection import ClickError
    from splatreplace_ns.instances.onnx_sam import OnnxModelError
    from splatreplace_ns.instances.from_clicks import SelectionError

    return (ClickError, DatasetFormatError, OnnxModelError, SelectionError, FileNotFoundError)


def error_lines(err: BaseException) -> str:
    """A user error as the user reads it: ``error: <problem>``, one line per problem found."""
    return "\n".join(f"error: {line}" for line in str(err).splitlines() or [type(err).__name__])


def install_excepthook() -> None:
    """Print an uncaught user error as :func:`error_lines` (the process still exits with status 1); every other
    exception keeps its traceback. Installed once, by our method's pipeline when it is made (``ns-train``,
    ``ns-eval``, ``ns-viewer`` on our runs), so that other methods keep nerfstudio's own handling."""
    previous = sys.excepthook
    if getattr(previous, "splatreplace_user_errors", False):
        return

    def hook(kind, value, traceback) -> None:
        if isinstance(value, user_error_types()):
            print(error_lines(value), file=sys.stderr)
        else:
            previous(kind, value, traceback)

    hook.splatreplace_user_errors = True
    sys.excepthook = hook
