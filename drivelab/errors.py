"""The one exception type that the CLI turns into a one-line message instead of a traceback."""


class DrivelabError(Exception):
    """Bad input from the user: a config field, an env id, a missing file.

    The message must fit on one line and name the offending field or file.
    """
