"""One exception type for every malformed-input case, with the file and view named."""

from __future__ import annotations


class DatasetError(ValueError):
    """A dataset cannot be loaded.

    Attributes:
        message: what is wrong, in words a user can act on.
        file: the offending file, relative to the dataset root when possible (or None).
        view: the index of the offending view (or None).
        code: a short machine-readable code, e.g. ``"missing_image"``, ``"size_mismatch"``.
    """

    def __init__(self, message: str, *, file: str | None = None, view: int | None = None,
                 code: str = "invalid_dataset") -> None:
        self.message = message
        self.file = file
        self.view = view
        self.code = code
        where = []
        if file is not None:
            where.append(f"file {file}")
        if view is not None:
            where.append(f"view {view}")
        prefix = f"[{', '.join(where)}] " if where else ""
        super().__init__(prefix + message)

    def to_dict(self) -> dict:
        """JSON-ready description: ``{"code", "message", "file", "view"}``."""
        return {"code": self.code, "message": self.message, "file": self.file, "view": self.view}
