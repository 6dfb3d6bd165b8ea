"""A stand-in for stderr in the progress-bar tests: it says whether it is a terminal and keeps
what is written to it."""


class Terminal:
    """A stderr that says it is a terminal (or not: ``tty``) and keeps what is written."""

    def __init__(self, tty=True):
        self.text, self.tty = "", tty

    def write(self, s):
        self.text += s

    def flush(self):
        pass

    def isatty(self):
        return self.tty
