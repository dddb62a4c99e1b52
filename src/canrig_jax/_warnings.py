"""The project's one warning class and the one way the library warns.

Every library warning is a ``CanrigWarning`` (a ``UserWarning``), attributed to the first
caller outside ``canrig_jax``: the line of the user's script that led to it, whichever
public function of the package found the problem and however deep inside the package.
Filter them all with ``warnings.filterwarnings("ignore", category=CanrigWarning)``.
"""

import contextlib
import os
import sys
import warnings
from collections.abc import Iterator

import jaxtyping

_PACKAGE_DIR = os.path.dirname(os.path.abspath(__file__)) + os.sep
_CHECKER_DIR = os.path.dirname(os.path.abspath(jaxtyping.__file__)) + os.sep
"""jaxtyping's wrappers: the test run's type check calls the package's functions through them."""


class CanrigWarning(UserWarning):
    """A warning from canrig_jax: the input is usable but probably not what was meant
    (a unit that makes a head 3 m tall, dropped frames in a take, a channel the rig ignores)."""


def user_stacklevel() -> int:
    """The ``stacklevel`` of ``warnings.warn`` (called by this function's caller) that points
    at the first frame outside the ``canrig_jax`` package."""
    frame = sys._getframe(2)  # the caller of the function that calls warnings.warn
    level = 2
    while frame is not None and frame.f_code.co_filename.startswith((_PACKAGE_DIR, _CHECKER_DIR)):
        frame = frame.f_back
        level += 1
    return level


def warn(message: str) -> None:
    """Issue ``message`` as a ``CanrigWarning`` at the user's call (the first frame outside
    the package)."""
    warnings.warn(message, CanrigWarning, stacklevel=user_stacklevel())


@contextlib.contextmanager
def print_warnings(prog: str) -> Iterator[None]:
    """For a command's duration, every warning shown is one ``PROG: warning: MESSAGE`` line on
    stderr, each message once, without the source file and line (a user of the command did
    not write them); a warning of another class than ``CanrigWarning`` is prefixed with its
    class name."""
    seen: set[str] = set()

    def show(message, category, filename, lineno, file=None, line=None) -> None:
        text = str(message)
        if not issubclass(category, CanrigWarning):
            text = f"{category.__name__}: {text}"
        if text not in seen:
            seen.add(text)
            print(f"{prog}: warning: {text}", file=sys.stderr, flush=True)

    with warnings.catch_warnings():
        warnings.simplefilter("always", CanrigWarning)  # each reaches show(), printed once
        warnings.showwarning = show
        yield
