"""Files that hold secrets: created with mode 0600 and never overwritten; refused when group or
others can read them (as ssh treats a private key)."""

import os
import stat
from pathlib import Path

from fleetmpc.errors import ConfigError

__all__ = ["check_private", "write_private"]


def write_private(path: Path, text: str, *, field: str) -> None:
    """Create `path` with mode 0600 holding `text`; ConfigError naming `field` if it exists."""
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except FileExistsError:
        raise ConfigError(field, f"{path} exists; not overwriting a secret") from None
    with os.fdopen(fd, "w", encoding="utf-8") as f:
        os.fchmod(f.fileno(), 0o600)  # (whatever the umask)
        f.write(text)


def check_private(path: Path, *, field: str) -> None:
    """ConfigError naming `field` unless `path` exists and only its owner may read it."""
    try:
        mode = Path(path).stat().st_mode
    except OSError as e:
        raise ConfigError(field, f"cannot read {path}: {e.strerror}") from None
    if mode & (stat.S_IRWXG | stat.S_IRWXO):
        raise ConfigError(
            field, f"{path} is readable by others (mode {stat.S_IMODE(mode):o}); chmod 600"
        )
