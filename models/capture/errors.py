"""The one error type of the capture format: a bad file or value, named."""


class CaptureError(ValueError):
    """A capture on disk (or in memory) breaks the format; the message names the file and the problem."""
