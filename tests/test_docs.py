"""The examples of README.md and docs/**/*.md work as written.

* Every ```python block runs: the blocks of one file in order in one namespace (as a reader types
  them), each file in a fresh namespace, with the working directory a fresh temporary directory.
* Every command line of a ``` block that starts with ``mkc-stream`` or ``python -m mkc_stream``
  (also after ``&&``, e.g. ``pip install ... && mkc-stream ...``) parses with the real parser,
  and the blocks run for real, in order, in a temporary directory.
* A block preceded by ``<!-- no-test: REASON -->`` (hardware: a serial device, a CAN bus) is not
  run; its command lines are still parsed. Other blocks (``pip``, ``python tools/...``, JSON
  shapes) are not examples this file can run.
"""
from __future__ import annotations

import pathlib
import re
import shlex
from dataclasses import dataclass

import numpy as np
import pytest

from mkc_stream.cli import build_parser, main

ROOT = pathlib.Path(__file__).resolve().parents[1]
DOC_FILES = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
FENCE = re.compile(r"^```([^\n`]*)\n(.*?)^```[ \t]*$", re.S | re.M)
NO_TEST = re.compile(r"^<!--\s*no-test:\s*(.*?)\s*-->\s*$")
#: a block that runs one of these takes tens of seconds (diagnose: up to ~60 s by its own docs)
SLOW_COMMANDS = {"diagnose"}


@dataclass(frozen=True)
class Block:
    path: pathlib.Path
    line: int            # 1-based line of the opening fence
    lang: str
    text: str
    no_test: str | None  # the reason of a <!-- no-test: ... --> right before the block

    @property
    def where(self) -> str:
        return f"{self.path.relative_to(ROOT)}:{self.line}"


def _blocks(path: pathlib.Path) -> list[Block]:
    text = path.read_text(encoding="utf-8")
    out = []
    for m in FENCE.finditer(text):
        before = text[:m.start()].rstrip("\n").splitlines()
        marker = NO_TEST.match(before[-1].strip()) if before else None
        out.append(Block(path, text.count("\n", 0, m.start()) + 1, m.group(1).strip(), m.group(2),
                         marker.group(1) if marker else None))
    return out


def _commands(block: Block) -> list[list[str]]:
    """The mkc-stream command lines of a block, as argv without the program name."""
    logical = block.text.replace("\\\n", " ").splitlines()
    cmds = []
    for line in logical:
        if "mkc-stream" not in line and "mkc_stream" not in line:
            continue                     # not a command of ours (and maybe not shell at all)
        tokens = shlex.split(line, comments=True)
        segment: list[str] = []
        for tok in tokens + ["&&"]:
            if tok != "&&":
                segment.append(tok)
                continue
            if segment[:1] == ["mkc-stream"]:
                cmds.append(segment[1:])
            elif segment[:3] == ["python", "-m", "mkc_stream"]:
                cmds.append(segment[3:])
            segment = []
    return cmds


ALL_BLOCKS = [b for f in DOC_FILES for b in _blocks(f)]
PY_FILES = sorted({b.path for b in ALL_BLOCKS if b.lang == "python"})
CMD_BLOCKS = [b for b in ALL_BLOCKS if b.lang in ("", "sh", "bash", "console", "shell") and _commands(b)]


def _rel(p: pathlib.Path) -> str:
    return str(p.relative_to(ROOT))


def test_the_examples_are_found():
    # a broken fence regex must not turn this file into a test of nothing
    assert ROOT / "README.md" in PY_FILES and len(PY_FILES) >= 3
    assert sum(len(_commands(b)) for b in CMD_BLOCKS) >= 10
    for f in DOC_FILES:                 # every marker belongs to the block right after it
        lines = f.read_text(encoding="utf-8").splitlines()
        for i, line in enumerate(lines):
            if NO_TEST.match(line.strip()):
                assert i + 1 < len(lines) and lines[i + 1].startswith("```"), f"{_rel(f)}:{i + 1}: dangling no-test"


# ----------------------------------------------------------------------------------------------
# python blocks
# ----------------------------------------------------------------------------------------------


def _check_readme(ns):
    assert np.abs(ns["fit"].hard_iron - ns["s"].hard_iron).max() < 0.1      # "~0.02 uT"
    assert ns["model"].coef_.shape == (2,)
    assert np.linalg.norm(ns["cal"].accepted.hard_iron - ns["s"].hard_iron) < 0.3


def _check_live(ns):
    assert ns["got"][1].seq == 1 and ns["got"][1].mag == (20.0, -3.0, 41.5)
    assert ns["port"].counts() == {"samples": 100, "bad_frames": 0, "drops": 0, "gaps": 0}
    assert ns["n_paced"] == 2000 and round(ns["clock"].slept, 1) == 40.0


def _check_diagnosis(ns):
    d = ns["d"]
    assert d.verdict == "explained" and d.selected == ["hard_iron_step"]
    assert d.effects[0].magnitude["value"] == pytest.approx(0.8, rel=0.05)


#: what the comments of the examples promise, per file
PY_CHECKS = {"README.md": _check_readme, "docs/live-and-recording.md": _check_live,
             "docs/diagnosis.md": _check_diagnosis}


@pytest.mark.parametrize("path", PY_FILES, ids=_rel)
def test_python_blocks_run(path, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("MPLBACKEND", "Agg")
    ns = {"__name__": "__doc_example__"}
    for b in (b for b in _blocks(path) if b.lang == "python"):
        if b.no_test:
            continue
        exec(compile(b.text, b.where, "exec"), ns)    # a failure names the file and its fence line
    check = PY_CHECKS.get(_rel(path))
    if check:
        check(ns)


# ----------------------------------------------------------------------------------------------
# mkc-stream command lines
# ----------------------------------------------------------------------------------------------


def _cmd_params():
    for b in CMD_BLOCKS:
        for k, argv in enumerate(_commands(b)):
            yield pytest.param(b, argv, id=f"{b.where}#{k + 1}:{argv[0] if argv else ''}")


@pytest.mark.parametrize("block,argv", list(_cmd_params()))
def test_command_line_parses(block, argv, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)          # output paths are checked against the working directory
    try:
        args = build_parser().parse_args(argv)
    except SystemExit as exc:
        pytest.fail(f"{block.where}: `mkc-stream {shlex.join(argv)}` does not parse (exit {exc.code})")
    assert getattr(args, "func", None), f"{block.where}: no subcommand in `mkc-stream {shlex.join(argv)}`"


def _run_params():
    for b in CMD_BLOCKS:
        slow = any(argv[:1] and argv[0] in SLOW_COMMANDS for argv in _commands(b))
        yield pytest.param(b, id=b.where, marks=[pytest.mark.slow] if slow else [])


@pytest.mark.parametrize("block", list(_run_params()))
def test_command_block_runs(block, tmp_path, monkeypatch, capsys):
    if block.no_test:
        pytest.skip(f"{block.where}: {block.no_test}")
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("MPLBACKEND", "Agg")
    for argv in _commands(block):
        code = main(argv)
        err = capsys.readouterr().err
        assert code == 0, f"{block.where}: `mkc-stream {shlex.join(argv)}` exited {code}: {err[-500:]}"


# ----------------------------------------------------------------------------------------------
# byte-level examples
# ----------------------------------------------------------------------------------------------


def test_the_binary_frame_example_is_what_the_encoder_writes():
    from mkc_stream.ingest.binary import encode_frame

    doc = ROOT / "docs" / "live-and-recording.md"
    text = doc.read_text(encoding="utf-8")
    assert "seq 0x1234, t 0x89ABCDEF us, m = (1, -2, 0.5) uT" in text
    [hexdump] = [b.text for b in _blocks(doc) if b.text.startswith("A5 5A ")]
    assert bytes.fromhex(hexdump.replace("|", " ")) == encode_frame(0x1234, 0x89ABCDEF, (1.0, -2.0, 0.5))
