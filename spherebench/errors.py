"""The one exception type for bad input, turned into a one-line message by the CLI."""

import importlib


class SphereBenchError(Exception):
    """Bad input or parameters: the message says what is wrong and what to do.

    The command line prints ``spherebench <command>: error: <message>`` and exits 2;
    library callers can catch it like any ValueError-style error.
    """


def require(module: str, extra: str, purpose: str):
    """Import an optional dependency, or raise a one-line SphereBenchError naming the extra that
    installs it (the core install leaves out torch, pyrealsense2, rerun-sdk and open3d)."""
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        raise SphereBenchError(f"{purpose} needs {module.split('.')[0]}, which cannot be imported ({exc}): "
                               f"pip install 'spherebench[{extra}]'") from None
