"""personalize: subject-specific lower-limb kinematic models from MRI and motion capture."""
from __future__ import annotations

try:
    from importlib.metadata import PackageNotFoundError, version as _version

    __version__ = _version("personalize")
except PackageNotFoundError:  # pragma: no cover - running from a source tree without installing
    __version__ = "0.1.0"
