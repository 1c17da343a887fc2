"""The error a ``terrain-nav`` command answers with one line and exit status 2."""


class InputError(ValueError):
    """Bad input to a command (an option, a file it names): the message says what is
    wrong and what to do about it."""
