"""The one exception type for bad input, turned into a one-line message by the CLI."""


class SphereBenchError(Exception):
    """Bad input or parameters: the message says what is wrong and what to do.

    The command line prints ``spherebench <command>: error: <message>`` and exits 2;
    library callers can catch it like any ValueError-style error.
    """
