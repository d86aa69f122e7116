"""The root of every cvvc-edge exception: the command line prints these as one line, never a traceback."""

__all__ = ["CvvcError"]


class CvvcError(Exception):
    """Base of every project exception. Messages say what is wrong and what to do about it."""
