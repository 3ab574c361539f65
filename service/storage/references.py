"""Model names and references ("name", "name:version", "name@alias"), and the topic names an upload or the
CLI may choose: the grammar alone, with no database, so the CLI and the request models check them before any
heavy import or work (`service.storage.registry` resolves references; the readers find topics).
"""
from __future__ import annotations

import re
from dataclasses import dataclass

from learnest.errors import InvalidInput

NAME = r"[A-Za-z0-9][A-Za-z0-9._-]{0,99}"
NAME_PATTERN = re.compile(rf"^{NAME}$")
REF_PATTERN = re.compile(rf"^(?P<name>{NAME})(?::(?P<version>[0-9]{{1,9}})|@(?P<alias>{NAME}))?$")


@dataclass(frozen=True)
class ModelRef:
    """A parsed model reference; ``str()`` gives it back as "name:version", "name@alias" or "name".

    Attributes
    ----------
    name : str
        Registered model name.
    version : int, optional
        Explicit version number.
    alias : str, optional
        Alias name (only when no version is given).
    """

    name: str
    version: int | None = None
    alias: str | None = None

    def __str__(self) -> str:
        if self.version is not None:
            return f"{self.name}:{self.version}"
        return f"{self.name}@{self.alias}" if self.alias else self.name


def parse_ref(text: str) -> ModelRef:
    """Parse "name:version", "name@alias" or "name" (surrounding spaces ignored).

    Raises
    ------
    InvalidInput
        If ``text`` has none of these forms.
    """
    match = REF_PATTERN.fullmatch((text or "").strip())
    if match is None:
        raise InvalidInput(f"model reference {text!r} must be 'name:version', 'name@alias' or 'name' (names: "
                      "1-100 letters, digits, '.', '_' or '-')")
    version = match["version"]
    return ModelRef(match["name"], int(version) if version else None, match["alias"])


def check_name(name: str, what: str = "model name") -> str:
    """``name`` unchanged if it is 1-100 letters, digits, '.', '_' or '-' starting with a letter or digit;
    else `InvalidInput` (``what`` names it in the message)."""
    if not NAME_PATTERN.fullmatch(name or ""):
        raise InvalidInput(f"{what} {name!r} must be 1-100 letters, digits, '.', '_' or '-' (starting with a "
                      "letter or digit)")
    return name


# A ROS topic name (letters, digits, "_", "/", "~"; JSON MCAP topics may also use "." and "-"), optionally
# with ":BODY", one body of a tf2_msgs/TFMessage or NamedPoseArray topic
TOPIC_PATTERN = re.compile(r"^/?[A-Za-z0-9_~][A-Za-z0-9_./~-]{0,199}(?::[A-Za-z0-9_][A-Za-z0-9_./-]{0,99})?$")


def check_topic(topic: str, what: str = "topic") -> str:
    """``topic`` without surrounding spaces if it is a topic name, optionally with ":BODY" (e.g. "/poses:cf1");
    else `InvalidInput` (``what`` names it in the message)."""
    text = (topic or "").strip()
    if not TOPIC_PATTERN.fullmatch(text):
        raise InvalidInput(f"{what} {topic!r} is not a topic name: letters, digits, '_', '/', '.', '-', '~' (at "
                           "most 200), optionally ':BODY' for one body of a /tf or NamedPoseArray topic, e.g. "
                           "/poses:cf1")
    return text
