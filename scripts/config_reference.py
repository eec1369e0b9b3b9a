"""Regenerate docs/guide/config.md from the config classes: every key, its default and its meaning
(the field's comment where the class is defined), the model section per registered kind.

    .venv/bin/python scripts/config_reference.py            # rewrite docs/guide/config.md
    .venv/bin/python scripts/config_reference.py --check    # exit 1 when it is out of date or a key has no meaning
"""
from __future__ import annotations

import ast
import dataclasses
import inspect
import os
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
os.environ["PNYOLO_PLUGINS"] = "0"  # pnyolo's own kinds, whatever other packages are installed

from pnyolo import config  # noqa: E402
from pnyolo.config import model as model_config  # noqa: E402
from pnyolo.registry import kinds  # noqa: E402

OUT = ROOT / "docs" / "guide" / "config.md"
INTRO = """# Configuration reference
Generated from the config classes by `scripts/config_reference.py` (a test keeps it current). A config
file (YAML) holds any subset of these keys; `--set section.key=value` overrides one. The `model`
section is the chosen kind's: every kind has `kind`, the kinds that read them have the reusable parts
`head`, `loss` (its loss weights) and `encoder`, and each kind adds its own sections; a `--set` of a key the
kind lacks is refused. The top-level `loss` section of older files still loads, moved into `model.loss` with a
one-line notice (`bev_heatmap` and `bev_box` are the ground-plane model's `heatmap` and `regression`).
Why each non-paper option exists and what it did on the benchmark: [docs/experiments.md](../experiments.md).
"""


def field_meanings(cls) -> dict[str, str]:
    """{field: its comment}: the comment on the field's line, else the comment lines just above it."""
    lines, start = inspect.getsourcelines(cls)
    tree = ast.parse("".join(lines))
    body = next(n for n in ast.walk(tree) if isinstance(n, ast.ClassDef)).body
    out = {}
    for node in body:
        if not isinstance(node, ast.AnnAssign) or not isinstance(node.target, ast.Name):
            continue
        row = node.lineno - 1
        text = lines[row].split("  # ", 1)[1].strip() if "  # " in lines[row] else ""
        k = row + 1
        while text and k < len(lines) and lines[k].strip().startswith("#   "):  # a trailing comment's continuation
            text += " " + lines[k].strip().lstrip("#").strip()
            k += 1
        if not text:
            above = []
            k = row - 1
            while k >= 0 and lines[k].strip().startswith("#") and not lines[k].strip().startswith("#   "):
                above.insert(0, lines[k].strip().lstrip("#").strip())
                k -= 1
            text = " ".join(above)
        out[node.target.id] = text
    return out


def rows(cls, prefix: str, missing: list[str]) -> list[str]:
    meaning = field_meanings(cls)
    out = []
    for f in dataclasses.fields(cls):
        if f.name == "kind" and prefix == "model":
            continue
        default = getattr(cls(), f.name)
        if dataclasses.is_dataclass(default):
            out += rows(type(default), f"{prefix}.{f.name}", missing)
            continue
        text = meaning.get(f.name) or next((m for c in inspect.getmro(cls)[1:] if dataclasses.is_dataclass(c)
                                            for n, m in field_meanings(c).items() if n == f.name), "")
        if not text:
            missing.append(f"{prefix}.{f.name}")
        out.append(f"| `{prefix}.{f.name}` | `{default!r}` | {text.replace('|', '/')} |")
    return out


def reference(missing: list[str]) -> str:
    parts = [INTRO]
    head = ["| key | default | meaning |", "|---|---|---|"]
    for section in ("data", "train", "eval"):
        cls = type(getattr(config.Config(), section))
        parts.append(f"\n## `{section}`\n\n" + "\n".join(head + rows(cls, section, missing)) + "\n")
    reusable = model_config.ImageModelConfig()  # every reusable part: head, the YOLO loss, encoder
    common = rows(type(reusable), "model", missing)
    parts.append("\n## `model`\n\n`model.kind` picks the class: " + ", ".join(f"`{k}`" for k in kinds())
                 + ". The reusable parts, in the kinds that read them (a detection head's settings, the YOLO loss's "
                 "weights, an image encoder):\n\n" + "\n".join(head + common) + "\n")
    for kind, cls in ((k, c.config_class) for k, c in kinds().items()):
        doc = (cls.__doc__ or "").strip().splitlines()[0]
        has = [f"`model.{f.name}`" for f in dataclasses.fields(cls) if f.name != "kind" and hasattr(reusable, f.name)
               and isinstance(getattr(cls(), f.name), type(getattr(reusable, f.name)))]
        doc += f" It has {', '.join(has)}." if has else ""
        own = [r for r in rows(cls, "model", missing) if r not in common]
        parts.append(f"\n### `model.kind: {kind}`\n\n{doc}"
                     + ("\n\n" + "\n".join(head + own) if own else " Nothing beyond these parts.") + "\n")
    return "".join(parts)


def main() -> int:
    missing: list[str] = []
    text = reference(missing)
    if "--check" in sys.argv[1:]:
        problems = [f"{OUT} is out of date: run {Path(__file__).name}"] if not OUT.is_file() or OUT.read_text() != text else []
        problems += [f"config keys without a meaning (a comment on or above the field): {sorted(set(missing))}"] if missing else []
        for p in problems:
            print(p, file=sys.stderr)
        return 1 if problems else 0
    OUT.write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
