"""The one exception type users see: a problem with their input, said in one line."""


class SelfshapeError(ValueError):
    """Bad input or an impossible request. ``str(err)`` is a one-line message that
    names the problem and where it is (file, entry, index)."""

    def __init__(self, message: str):
        super().__init__(" ".join(str(message).split()))
