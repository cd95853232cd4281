"""The job's ``error`` text: a message a user can act on, without the server's paths."""

from __future__ import annotations

from typing import TYPE_CHECKING

from jobstore.storage import StorageUnavailable

if TYPE_CHECKING:
    from jobstore.settings import Settings


def human_error(exc: BaseException) -> str:
    """A message a user can act on, for the job's ``error`` field."""
    if hasattr(exc, "to_dict") and hasattr(exc, "message"):          # DatasetError
        return f"invalid dataset: {exc}"
    name = type(exc).__name__
    text = str(exc).strip()
    if isinstance(exc, StorageUnavailable):   # never the dataset's fault
        return (f"the object store was unreachable, so the job could not go on ({text}); the dataset is "
                "fine: upload it again once the store answers")
    if "out of memory" in text.lower() or isinstance(exc, MemoryError):
        return f"out of memory while training ({name}); try the 'fast' or 'tiny' preset or a smaller dataset"
    if isinstance(exc, NotImplementedError):
        return f"not available in this NePF version: {text or name}"
    if isinstance(exc, FileNotFoundError):
        return f"a file the job needs is missing: {text}"
    return f"training failed: {name}: {text}" if text else f"training failed: {name}"


def scrub_server_paths(message: str, settings: Settings) -> str:
    """``message`` without the data dir's absolute path (``<data dir>`` instead): a job's error is
    an API response, and an ``OSError`` names the file it failed on."""
    return message.replace(str(settings.data_path), "<data dir>")
