"""Exceptions that reach the user as one clear line (exit code 2)."""


class InputError(Exception):
    """Bad user input: a missing image, a bad camera string, too little overlap, ...

    The CLI prints ``str(err)`` on one line and exits with code 2.
    """
