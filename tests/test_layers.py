"""The package's layers: no module imports from a layer above its own, and no module grows past
MAX_LINES without saying why.

Imports are read from the source (ast), lazy ones inside functions included, as are
``importlib.import_module("mkc_stream....")`` calls with a literal name. A module may import its own
layer and the layers below it. Every top-level module or subpackage of mkc_stream/ must be placed in
LAYERS: a new one is a decision about where it sits.
"""
from __future__ import annotations

import ast
import pathlib

import pytest

PACKAGE = pathlib.Path(__file__).resolve().parents[1] / "mkc_stream"

#: bottom to top; each entry is a top-level module or subpackage of mkc_stream ("__init__" is the
#: package itself)
LAYERS = [
    # foundations: the Numba kernels and the small shared helpers they and everything else use
    {"kernels", "_numba", "_validation", "_lazy", "robust", "jsonout", "units", "recording_rules", "state", "defaults"},
    # estimators, the calibration, recordings; the analytic helpers and plots; the parameter files
    {"batch", "stream", "verify", "baselines", "calib", "io", "pdf", "bounds", "plots", "params"},
    # the simulator, the live sources, and the calibration from flight logs (whose simulated
    # flights use the simulator), over recordings and the calibration
    {"sim", "ingest", "flight"},
    # the diagnoser (over the simulator) and the bridge to the C port (over the calibrator)
    {"diagnose", "cport", "firmware"},
    # the subcommands (commands/common.py is what they share)
    {"commands"},
    # the command line: builds the parser, registers the commands, runs the top-level handler
    {"cli"},
    # the package's lazy exports and `python -m mkc_stream`
    {"__init__", "__main__"},
]
LAYER_OF = {name: k for k, names in enumerate(LAYERS) for name in names}

#: modules longer than this say why in their docstring, on a line containing "Size:"
MAX_LINES = 600
#: over the limit while a split is under way elsewhere (remove the entry when it lands)
#: modules over MAX_LINES on their way to a split (none today)
PENDING_SPLIT: dict = {}

MODULES = sorted(PACKAGE.rglob("*.py"))


def module_name(path: pathlib.Path) -> str:
    parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def unit(name: str) -> str:
    """The LAYERS key of a dotted module name under mkc_stream."""
    parts = name.split(".")
    return parts[1] if len(parts) > 1 else "__init__"


def is_module(name: str) -> bool:
    rel = pathlib.Path(*name.split(".")[1:]) if "." in name else pathlib.Path()
    return (PACKAGE / rel).with_suffix(".py").is_file() or (PACKAGE / rel / "__init__.py").is_file()


def imports_of(path: pathlib.Path) -> list[tuple[int, str]]:
    """(line, dotted module under mkc_stream) of every import in the file, at any depth."""
    name = module_name(path)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names if a.name.split(".")[0] == "mkc_stream"]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if target.split(".")[0] != "mkc_stream":
                continue
            # `from . import x` / `from ..cport import compare`: the submodule when x is one
            subs = [f"{target}.{a.name}" for a in node.names if is_module(f"{target}.{a.name}")]
            out += [(node.lineno, t) for t in subs] or [(node.lineno, target)]
        elif (isinstance(node, ast.Call) and getattr(node.func, "attr", getattr(node.func, "id", None)) == "import_module"
              and node.args and isinstance(node.args[0], ast.Constant) and isinstance(node.args[0].value, str)
              and node.args[0].value.startswith("mkc_stream")):
            out.append((node.lineno, node.args[0].value))
    return out


def test_every_module_has_a_layer():
    missing = sorted({unit(module_name(p)) for p in MODULES} - set(LAYER_OF))
    assert not missing, f"place these in LAYERS of tests/test_layers.py: {missing}"


def test_no_module_imports_from_a_layer_above_it():
    bad = []
    for path in MODULES:
        src = module_name(path)
        for line, target in imports_of(path):
            here, there = LAYER_OF.get(unit(src)), LAYER_OF.get(unit(target))
            if there is None:
                bad.append(f"{path.relative_to(PACKAGE.parent)}:{line}: {target} is in no layer")
            elif here is not None and there > here:
                bad.append(f"{path.relative_to(PACKAGE.parent)}:{line}: imports {target} "
                           f"(layer {there}: {unit(target)}) from layer {here} ({unit(src)})")
    assert not bad, "\n".join(bad)


def test_the_checker_sees_lazy_and_relative_imports():
    """The parser itself: a relative import inside a function is found and resolved to the submodule."""
    got = {t for _, t in imports_of(PACKAGE / "commands" / "crosscheck.py")}
    assert "mkc_stream.cport" in got                      # `from .. import cport as FW`, inside cmd_crosscheck
    assert "mkc_stream.commands.common" in got            # `from .common import ...`, at the top
    assert "mkc_stream.commands.argtypes" in got          # `from .argtypes import input_file`, inside register
    assert "mkc_stream.commands.common" in {t for _, t in imports_of(PACKAGE / "cli.py")}


@pytest.mark.parametrize("path", MODULES, ids=lambda p: str(p.relative_to(PACKAGE)))
def test_modules_over_the_size_limit_say_why(path):
    rel = str(path.relative_to(PACKAGE))
    lines = len(path.read_text(encoding="utf-8").splitlines())
    if lines <= MAX_LINES or rel in PENDING_SPLIT:
        return
    doc = ast.get_docstring(ast.parse(path.read_text(encoding="utf-8"))) or ""
    assert any("Size:" in line for line in doc.splitlines()), (
        f"{rel} has {lines} lines (> {MAX_LINES}): split it, or give the reason on a 'Size:' line of its docstring")
