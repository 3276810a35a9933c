"""Where the ``spherebench`` command's caches go: one folder that the user can set.

The folder is ``$SPHEREBENCH_CACHE_DIR``, else ``$XDG_CACHE_HOME/spherebench``, else
``~/.cache/spherebench`` (where it cannot be made, as under a HOME that is a file,
``$TMPDIR/spherebench-cache-<uid>``). The libraries that keep a cache each get a sub-folder of
it, through their own variable, unless the user has set that variable: numba's compiled kernels
(which it would otherwise keep beside the installed package, or in ``~/.cache/numba`` where that
is read-only), matplotlib's font list (``~/.cache/matplotlib``, with an empty
``~/.config/matplotlib``) and torch's inductor folder (``$TMPDIR/torchinductor_<user>``, which
torch makes when an optimiser is built even though nothing is compiled). A program that imports
the package keeps the libraries' own places unless it calls ``use_cache_folder`` before importing
them.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

#: the variable that names the cache folder
CACHE_VARIABLE = "SPHEREBENCH_CACHE_DIR"

#: a library's cache variable -> its sub-folder of the cache folder
LIBRARY_FOLDERS = {
    "NUMBA_CACHE_DIR": "numba",  # read when numba is imported
    "MPLCONFIGDIR": "matplotlib",  # matplotlib's configuration and cache folder in one
    "TORCHINDUCTOR_CACHE_DIR": "torch",  # read when the folder is first needed
}


def cache_folder(environ=os.environ) -> Path | None:
    """The cache folder that ``environ`` (a mapping of variables) names, as an absolute path; None
    where it names none and the user has no home folder (no HOME and no password entry)."""
    own = environ.get(CACHE_VARIABLE)
    if own:
        return Path(own).expanduser().absolute()
    xdg = environ.get("XDG_CACHE_HOME")
    if xdg and Path(xdg).is_absolute():  # a relative one is to be ignored (XDG base directories)
        return Path(xdg) / "spherebench"
    try:
        home = Path(environ["HOME"]) if environ.get("HOME") else Path.home()  # Path.home(): HOME, else the user's entry
    except (RuntimeError, KeyError):
        return None
    return home.absolute() / ".cache" / "spherebench"


def _can_make(folder: Path) -> bool:
    """Whether ``folder`` is there or can be made: its nearest existing part is a folder this user
    may write in (a HOME that is a file, or read-only, leaves the libraries their own places)."""
    for part in (folder, *folder.parents):
        if part.exists():
            return part.is_dir() and os.access(part, os.W_OK | os.X_OK)
    return False


def use_cache_folder(environ=os.environ) -> Path | None:
    """Point each library of ``LIBRARY_FOLDERS`` whose variable is unset in ``environ`` at its
    sub-folder of the cache folder, or where that cannot be made, of ``$TMPDIR/spherebench-cache-<uid>``;
    returns the folder (None: neither can be made, and the libraries keep their own places).
    Nothing is created here: each library makes its folder when it first writes there (a command
    that refuses its input makes none). Worker processes inherit the variables."""
    folder = cache_folder(environ)
    if folder is None or not _can_make(folder):
        # no home to hold it (none, a file, read-only): the temporary folder, one per user, rather
        # than each library's own fallback (matplotlib's is a new temporary folder and a warning a run)
        folder = Path(tempfile.gettempdir()).absolute() / f"spherebench-cache-{os.getuid()}"
        if not _can_make(folder):
            return None
    for variable, name in LIBRARY_FOLDERS.items():
        if not environ.get(variable):
            environ[variable] = str(folder / name)
    return folder
