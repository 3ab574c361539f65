"""A simple file store for trained models under LEARNEST_HOME (the registry replaces it later)."""
from __future__ import annotations

import os
import re
from pathlib import Path

from models.knode import HybridModel

NAME_PATTERN = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,99}$")


def home() -> Path:
    return Path(os.environ.get("LEARNEST_HOME", ".learnest"))


def _model_path(name: str) -> Path:
    if not NAME_PATTERN.fullmatch(name or ""):  # names never become arbitrary paths
        raise ValueError(f"model name {name!r} must be 1-100 letters, digits, '.', '_' or '-'")
    return home() / "models" / f"{name}.json"


def save_model(model: HybridModel, name: str) -> Path:
    path = _model_path(name)
    path.parent.mkdir(parents=True, exist_ok=True)
    model.meta["name"] = name
    model.save(path)
    return path


def load_model(name: str) -> HybridModel:
    path = _model_path(name)
    if not path.exists():
        known = sorted(p.stem for p in (home() / "models").glob("*.json"))
        raise ValueError(f"no model named {name!r} in {home()} (known: {', '.join(known) or 'none'})")
    return HybridModel.load(path)
