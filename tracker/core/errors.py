"""Errors meant for the person at the keyboard."""


class UserError(Exception):
    """Bad input that the user can fix. The CLI prints the message on one line and exits
    non-zero, without a traceback; keep the message short and say what to do."""
