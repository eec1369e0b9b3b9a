"""The house rules, checked mechanically: small files and functions everywhere, one way for imports
(tests/pnyolo/models/test_pnyolo_model_interface.py), and a benchmark that names no model kind (the kinds speak for
themselves, the presets name them)."""
from __future__ import annotations

import ast
import re

import pytest

from pnyolo.registry import kinds
from repo_paths import REPO

ROOT = REPO
PACKAGES = ("blender_tools", "dataset_spec", "tools", "pnyolo", "benchmarks", "scripts", "tests")
MAX_LINES, MAX_FUNCTION = 400, 80


def _sources():
    return sorted(p for pkg in PACKAGES for p in (ROOT / pkg).rglob("*.py"))


def test_no_source_file_over_400_lines_and_no_function_over_80():
    big = [f"{p.relative_to(ROOT)} ({n})" for p in _sources() if (n := len(p.read_text().splitlines())) > MAX_LINES]
    long = [f"{p.relative_to(ROOT)}:{node.name} ({node.end_lineno - node.lineno + 1})"
            for p in _sources() for node in ast.walk(ast.parse(p.read_text()))
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef))
            and node.end_lineno - node.lineno + 1 > MAX_FUNCTION]
    assert not big and not long, (big, long)


def test_no_pnyolo_function_takes_more_than_8_parameters():
    """Issue 66: what travels together travels as one value (a bundle), not as a long parameter list; self and
    cls are not counted, a command's ``main`` is excepted."""
    found = []
    for p in sorted((ROOT / "pnyolo").rglob("*.py")):
        for n in ast.walk(ast.parse(p.read_text())):
            if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef)) and n.name != "main":
                a = n.args
                count = sum(x.arg not in ("self", "cls") for x in a.posonlyargs + a.args + a.kwonlyargs)
                count += (a.vararg is not None) + (a.kwarg is not None)
                if count > 8:
                    found.append(f"{p.relative_to(ROOT)}:{n.lineno} {n.name} ({count})")
    assert not found, found


def test_the_bench_names_no_model_kind():
    names = "|".join(re.escape(k) for k in kinds())
    found = [f"{p.relative_to(ROOT)}:{k}: {line.strip()}" for p in sorted((ROOT / "pnyolo" / "bench").rglob("*.py"))
             for k, line in enumerate(p.read_text().splitlines(), 1)
             if re.search(rf"(?<![\w-])({names})(?![\w-])", line)]
    assert not found, found


def test_evaluation_and_the_bench_pin_no_device():
    """No "cpu" string in the code that evaluates, decodes, tracks or benchmarks (issue 64: the bench once passed
    "cpu" everywhere and ran its whole test stage on the CPU beside an idle GPU); docstrings may say it, and a
    comparison may ask whether a tensor is there (``t.device.type != "cpu"``), which moves nothing."""
    folders = [ROOT / "pnyolo" / d for d in ("evaluation", "bench", "decoding", "tracking")]
    found = []
    for p in sorted(f for d in folders for f in d.rglob("*.py")):
        tree = ast.parse(p.read_text())
        docs = {id(n.body[0].value) for n in ast.walk(tree)
                if isinstance(n, (ast.Module, ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)) and n.body
                and isinstance(n.body[0], ast.Expr) and isinstance(n.body[0].value, ast.Constant)}
        asked = {id(c) for n in ast.walk(tree) if isinstance(n, ast.Compare) for c in n.comparators}
        found += [f"{p.relative_to(ROOT)}:{n.lineno}" for n in ast.walk(tree)
                  if isinstance(n, ast.Constant) and n.value == "cpu" and id(n) not in docs | asked]
    assert not found, found


def test_an_operating_point_is_a_value_nothing_writes_into_a_config_s_eval():
    """Issue 86 item 1: the thresholds and NMS settings that define "the model as chosen" are a value: the choosers
    and the commands make a new one (``dataclasses.replace``), so the same predictions decode the same way whenever
    they are read. EvalConfig is frozen (a write is an error at run time) and no source assigns into one."""
    import ast
    import dataclasses

    from pnyolo.config import EvalConfig

    with pytest.raises(dataclasses.FrozenInstanceError):
        EvalConfig().conf_threshold = 0.1
    writes = []
    for path in sorted((ROOT / "pnyolo").rglob("*.py")) + sorted((ROOT / "benchmarks").glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target] if isinstance(
                node, (ast.AugAssign, ast.AnnAssign)) else []
            for t in (e for t in targets for e in (t.elts if isinstance(t, ast.Tuple) else [t])):
                if isinstance(t, ast.Attribute) and isinstance(t.value, ast.Attribute) and t.value.attr == "eval":
                    writes.append(f"{path.relative_to(ROOT)}:{node.lineno}")
            if isinstance(node, ast.Call) and getattr(node.func, "id", "") == "setattr" and node.args and \
                    isinstance(node.args[0], ast.Attribute) and node.args[0].attr == "eval":
                writes.append(f"{path.relative_to(ROOT)}:{node.lineno}")
    assert writes == [], writes
