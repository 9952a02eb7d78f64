"""Where the package's configuration and shipped checkpoints live, installed or not."""

from __future__ import annotations

import os
import sys
from pathlib import Path

_REPO = Path(__file__).resolve().parent.parent


def share_dir() -> Path:
    """The directory holding ``config/`` and ``checkpoints/``.

    ``W2E_SHARE_DIR`` wins; then the source tree (editable installs, tests); then the ament
    share directory of an installed package.
    """
    env = os.environ.get("W2E_SHARE_DIR")
    if env:
        return Path(env)
    if (_REPO / "config" / "categories.yaml").exists():
        return _REPO
    return Path(sys.prefix) / "share" / "w2e_ros"


def config_dir() -> Path:
    return share_dir() / "config"


def checkpoint_dir() -> Path:
    return share_dir() / "checkpoints"


def default_checkpoint(primitive: str) -> Path:
    """The shipped default model (combination cfw) for a base primitive."""
    return checkpoint_dir() / f"w2e_cfw_{primitive}.pt"


def default_replay_pack() -> Path:
    """The shipped replay sample of the default models' training data (``w2e replay-pack``)."""
    return checkpoint_dir() / "replay_cfw"
