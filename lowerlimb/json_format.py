"""JSON text as the toolkit writes it: indented, with innermost number lists kept on one line."""
from __future__ import annotations

import json
import re

__all__ = ["json_text"]


def json_text(obj) -> str:
    """Indented JSON with innermost number lists kept on one line."""
    text = json.dumps(obj, indent=2)
    return re.sub(r"\[\s*([-0-9.eE+, \n\r\tnulltruefals]*?)\s*\]",
                  lambda m: "[" + ", ".join(t.strip() for t in m.group(1).split(",")) + "]"
                  if m.group(1).strip() else "[]", text)
