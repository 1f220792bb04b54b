#!/usr/bin/env python3
"""Runs every code block of README.md and docs/**/*.md as written.

    PIPE=target/release/pipe .venv/bin/python tests/docs/run_snippets.py [-k TEXT] [--list]

Fenced blocks by language:

- ``yaml``: a whole pipeline (has `name` and `stages`) is checked with `pipe validate`; a
  fragment (a list of steps, or a mapping with `stages` and/or `export`) is wrapped into a
  pipeline first, or merged into the pipeline a marker names (steps with the same id and
  exports with the same `to` are replaced, others appended);
- ``sh`` / ``bash``: run by bash (`set -eo pipefail`) in the scratch directory, with `pipe`
  on PATH;
- ``python``: run by the venv's python in the scratch directory;
- ``text``, ``rust``, ``toml``, ``c``: shown, not run. A block without a language is an
  error: say what it is.

Markers, an HTML comment on the line(s) just above the fence (invisible on GitHub):

    <!-- snippet: skip (why) -->             not run; the reason is required
    <!-- snippet: run -->                    yaml: `pipe run` instead of `pipe validate`
    <!-- snippet: into pipelines/X.yaml -->  yaml: a fragment of that pipeline
    <!-- snippet: validate (why) -->         sh: `pipe run` becomes `pipe validate` and
                                             `pipe sweep` validates each varied value; for
                                             commands that would run for minutes
    <!-- snippet: needs pipelines/X.yaml --> run that pipeline first

Blocks run in a scratch directory whose entries link to the repository's (pipelines/,
data/, examples/, ...), so `out/`, `runs/` and the step cache are the scratch's own. A block
that names a file under `out/` that a pipeline in pipelines/ exports gets that pipeline run
first (once per session), so examples may read the outputs of shipped pipelines.
"""

from __future__ import annotations

import argparse
import os
import re
import shlex
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[2]
RUN_LANGS = {"yaml", "yml", "sh", "bash", "python", "py"}
SHOWN_LANGS = {"text", "rust", "toml", "c", "json", "console-output"}
# Not linked into the scratch directory: what blocks write must not land in the tree.
PRIVATE = {".git", "out", "runs", ".grainpipe-cache", "target"}
BLOCK_TIMEOUT = 240


@dataclass
class Block:
    path: Path
    line: int  # 1-based line of the opening fence
    lang: str
    text: str
    markers: dict[str, str] = field(default_factory=dict)

    @property
    def where(self) -> str:
        return f"{shown(self.path)}:{self.line}"


MARKER = re.compile(r"^\s*<!--\s*snippet:\s*(\w+)\s*(.*?)\s*-->\s*$")
FENCE = re.compile(r"^( {0,3})(`{3,}|~{3,})\s*([^\s`]*)")


def parse_markers(lines: list[str], fence_index: int, where: str) -> dict[str, str]:
    markers: dict[str, str] = {}
    i = fence_index - 1
    while i >= 0 and MARKER.match(lines[i]):
        m = MARKER.match(lines[i])
        kind, arg = m.group(1), m.group(2).strip()
        if kind not in {"skip", "run", "into", "validate", "needs"}:
            raise SystemExit(
                f"{where}: unknown snippet marker `{kind}` "
                "(use skip, run, into, validate or needs)"
            )
        if kind in {"skip", "validate"} and not re.fullmatch(r"\(.+\)", arg):
            raise SystemExit(
                f"{where}: `snippet: {kind}` needs a reason in parentheses, "
                f"e.g. <!-- snippet: {kind} (runs for minutes) -->"
            )
        if kind in {"into", "needs"} and not (REPO / arg).is_file():
            raise SystemExit(f"{where}: `snippet: {kind} {arg}`: no such file in the repository")
        markers[kind] = markers[kind] + " " + arg if kind == "needs" and kind in markers else arg
        i -= 1
    return markers


def shown(path: Path) -> str:
    """A path as messages show it: relative to the repository when inside it."""
    try:
        return str(path.relative_to(REPO))
    except ValueError:
        return str(path)


def extract(path: Path) -> list[Block]:
    lines = path.read_text(encoding="utf-8").split("\n")
    blocks: list[Block] = []
    i = 0
    while i < len(lines):
        m = FENCE.match(lines[i])
        if not m:
            i += 1
            continue
        indent, fence, lang = m.group(1), m.group(2), m.group(3).lower()
        start = i
        body: list[str] = []
        i += 1
        while i < len(lines) and not re.match(
            rf"^ {{0,3}}{fence[0]}{{{len(fence)},}}\s*$", lines[i]
        ):
            body.append(lines[i][len(indent):] if lines[i].startswith(indent) else lines[i])
            i += 1
        if i == len(lines):
            raise SystemExit(f"{shown(path)}:{start + 1}: code block never closed")
        where = f"{shown(path)}:{start + 1}"
        if not lang:
            raise SystemExit(
                f"{where}: code block without a language: mark it `sh`, `yaml` or `python` "
                "(run by this test) or `text` (shown only)"
            )
        blocks.append(Block(path, start + 1, lang, "\n".join(body) + "\n",
                            parse_markers(lines, start, where)))
        i += 1
    return blocks


def doc_files() -> list[Path]:
    files = [REPO / "README.md"]
    files += sorted((REPO / "docs").rglob("*.md"))
    return files


class Session:
    def __init__(self, pipe: Path, python: Path, scratch: Path, verbose: bool):
        self.pipe, self.python, self.scratch, self.verbose = pipe, python, scratch, verbose
        self.ran_pipelines: dict[str, bool] = {}
        self.exports = self._exports()
        bin_dir = scratch / ".snippet-bin"
        bin_dir.mkdir(exist_ok=True)
        (bin_dir / "pipe").unlink(missing_ok=True)
        (bin_dir / "pipe").symlink_to(pipe)
        vbin = scratch / ".snippet-bin-validate"
        vbin.mkdir(exist_ok=True)
        shim = vbin / "pipe"
        shim.write_text(
            f"#!/bin/sh\nexec {shlex.quote(str(python))} {shlex.quote(str(Path(__file__)))} "
            f"--shim {shlex.quote(str(pipe))} \"$@\"\n"
        )
        shim.chmod(0o755)
        self.bin_dir, self.validate_bin = bin_dir, vbin

    def _exports(self) -> dict[str, str]:
        """Export path -> the pipeline file that writes it (the first one, by name)."""
        out: dict[str, str] = {}
        for p in sorted((REPO / "pipelines").glob("*.yaml")):
            try:
                doc = yaml.safe_load(p.read_text())
            except yaml.YAMLError:
                continue
            for e in (doc or {}).get("export") or []:
                to = e.get("to") if isinstance(e, dict) else None
                if isinstance(to, str):
                    out.setdefault(to, f"pipelines/{p.name}")
        return out

    def env(self, validate_only: bool = False) -> dict[str, str]:
        env = dict(os.environ)
        first = self.validate_bin if validate_only else self.bin_dir
        env["PATH"] = f"{first}:{self.python.parent}:{env.get('PATH', '')}"
        env["PIPE"] = str(self.pipe)
        env["PYTHONDONTWRITEBYTECODE"] = "1"
        return env

    def run(self, cmd: list[str], what: str, validate_only: bool = False) -> tuple[bool, str]:
        try:
            r = subprocess.run(cmd, cwd=self.scratch, env=self.env(validate_only),
                               capture_output=True, text=True, timeout=BLOCK_TIMEOUT)
        except subprocess.TimeoutExpired:
            return False, f"{what}: timed out after {BLOCK_TIMEOUT} s"
        out = (r.stdout + r.stderr).strip()
        if r.returncode != 0:
            return False, f"{what}: exit code {r.returncode}\n{out}"
        return True, out

    def prerequisites(self, block: Block) -> list[str]:
        needs = block.markers.get("needs", "").split()
        if block.lang in {"yaml", "yml"}:
            # A pipeline's own exports are what it writes, not what it needs.
            text = "\n".join(l for l in block.text.splitlines() if "to:" not in l)
        else:
            text = block.text
        for path in re.findall(r"out/[\w.\-/]+[\w]", text):
            if path in self.exports:
                needs.append(self.exports[path])
        return list(dict.fromkeys(needs))

    def ensure(self, pipeline: str) -> tuple[bool, str]:
        if pipeline not in self.ran_pipelines:
            t = time.monotonic()
            ok, msg = self.run([str(self.pipe), "run", pipeline, "--quiet"], f"pipe run {pipeline}")
            self.ran_pipelines[pipeline] = ok
            print(f"  (ran {pipeline} first: {time.monotonic() - t:.1f} s)", flush=True)
            if not ok:
                return False, msg
        return self.ran_pipelines[pipeline], f"prerequisite {pipeline} failed"


def merge(base: dict, frag, where: str) -> dict:
    if isinstance(frag, list):
        frag = {"stages": frag}
    if not isinstance(frag, dict):
        raise ValueError(f"{where}: a YAML fragment must be a list of steps or a mapping")
    out = dict(base)
    for key, value in frag.items():
        if key in {"stages", "export"} and isinstance(value, list):
            ident = "id" if key == "stages" else "to"
            merged = list(out.get(key) or [])
            for item in value:
                idx = next((k for k, old in enumerate(merged)
                            if isinstance(old, dict) and isinstance(item, dict)
                            and old.get(ident) == item.get(ident)), None)
                if idx is None:
                    merged.append(item)
                else:
                    merged[idx] = item
            out[key] = merged
        else:
            out[key] = value
    return out


def check_yaml(s: Session, block: Block, n: int) -> tuple[bool, str]:
    try:
        doc = yaml.safe_load(block.text)
    except yaml.YAMLError as e:
        return False, f"not valid YAML: {e}"
    target = block.markers.get("into")
    whole = not target and isinstance(doc, dict) and "name" in doc
    if target:
        base = yaml.safe_load((REPO / target).read_text())
        try:
            doc = merge(base, doc, block.where)
        except ValueError as e:
            return False, str(e)
    elif isinstance(doc, list) or (isinstance(doc, dict) and "name" not in doc):
        doc = merge({"name": f"snippet-{n}", "stages": []}, doc, block.where)
    snippet_dir = s.scratch / ".snippets"
    snippet_dir.mkdir(exist_ok=True)
    stem = re.sub(r"[^\w]+", "-", block.where)
    file = snippet_dir / f"{stem}.yaml"
    # A whole pipeline is written as it stands, so line numbers in messages match the page.
    file.write_text(block.text if whole else yaml.safe_dump(doc, sort_keys=False))
    verb = "run" if "run" in block.markers else "validate"
    cmd = [str(s.pipe), verb, str(file)] + (["--quiet"] if verb == "run" else [])
    return s.run(cmd, f"pipe {verb} ({'merged into ' + target if target else 'as written'})")


def check_sh(s: Session, block: Block, n: int) -> tuple[bool, str]:
    script = "set -eo pipefail\n" + block.text
    return s.run(["bash", "-c", script], "bash", validate_only="validate" in block.markers)


def check_python(s: Session, block: Block, n: int) -> tuple[bool, str]:
    stem = re.sub(r"[^\w]+", "-", block.where)
    file = s.scratch / ".snippets" / f"{stem}.py"
    file.parent.mkdir(exist_ok=True)
    file.write_text(block.text)
    return s.run([str(s.python), str(file)], "python")


CHECKS = {"yaml": check_yaml, "yml": check_yaml, "sh": check_sh, "bash": check_sh,
          "python": check_python, "py": check_python}


def split_values(values: str) -> list[str]:
    """`a,b,[c,d]` -> ['a', 'b', '[c,d]']: commas inside brackets or braces do not split."""
    out, depth, cur = [], 0, ""
    for ch in values:
        if ch in "[{":
            depth += 1
        elif ch in "]}":
            depth -= 1
        if ch == "," and depth == 0:
            out.append(cur)
            cur = ""
        else:
            cur += ch
    out.append(cur)
    return out


def shim(pipe: str, args: list[str]) -> int:
    """`pipe` in validate-only blocks: checks what a long command would run, runs nothing."""
    run_only_flags = {"--report", "--no-cache", "--quiet", "-q", "--retry-failed"}
    run_only_values = {"--out", "--threads", "--cache-dir", "--jobs", "--realizations",
                       "--executor", "--time", "--cpus-per-task",
                       "--sbatch-option", "--rve-volume", "--point-variance", "--metric",
                       "--target-error"}
    if not args or args[0] not in {"run", "sweep", "study"}:
        if args and args[0] == "report":
            print("validate-only block: `pipe report` needs the run; not checked")
            return 0
        return subprocess.call([pipe] + args)
    kept, varied, i = [], [], 1
    while i < len(args):
        a = args[i]
        key = a.split("=", 1)[0]
        if key in run_only_flags:
            i += 1
        elif key in run_only_values:
            i += 1 if "=" in a else 2
        elif key == "--collect":
            # The collected step must exist: `--target STEP` makes validate say so.
            value = a.split("=", 1)[1] if "=" in a else args[i + 1]
            kept += ["--target", value.split(".")[0]]
            i += 1 if "=" in a else 2
        elif key == "--vary":
            varied.append(a.split("=", 1)[1] if "=" in a else args[i + 1])
            i += 1 if "=" in a else 2
        else:
            kept.append(a)
            i += 1
    sets: list[list[str]] = [[]]
    for v in varied:
        k, values = v.split("=", 1)
        vals = split_values(values)
        if len(vals) == 1 and re.fullmatch(r"[^:]+:[^:]+:\d+", vals[0]):
            vals = vals[0].split(":")[:2]  # a:b:n -> the two ends
        sets += [["--set", f"{k}={x}"] for x in vals]
    for extra in sets:
        code = subprocess.call([pipe, "validate"] + kept + extra, stdout=subprocess.DEVNULL)
        if code != 0:
            print(f"pipe validate {' '.join(kept + extra)}: exit {code}", file=sys.stderr)
            return code
    return 0


def main() -> int:
    if len(sys.argv) > 2 and sys.argv[1] == "--shim":
        return shim(sys.argv[2], sys.argv[3:])
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("-k", help="only blocks whose file:line contains this text")
    ap.add_argument("--list", action="store_true", help="list the blocks and what is done")
    ap.add_argument("--scratch", help="scratch directory (kept; default: a fresh temporary one)")
    ap.add_argument("-v", "--verbose", action="store_true", help="print each block's output")
    ap.add_argument("files", nargs="*", type=Path,
                    help="markdown files (default: README.md and docs/**/*.md)")
    args = ap.parse_args()

    files = [f.resolve() for f in args.files] or doc_files()
    blocks = [b for f in files for b in extract(f)]
    if args.k:
        blocks = [b for b in blocks if args.k in b.where]
    if args.list:
        for b in blocks:
            todo = ("skip " + b.markers["skip"] if "skip" in b.markers else
                    "run" if b.lang in RUN_LANGS else "shown")
            print(f"{b.where:40} {b.lang:8} {todo} {' '.join(f'{k}={v}' for k, v in b.markers.items() if k != 'skip')}")
        return 0
    unknown = [b for b in blocks if b.lang not in RUN_LANGS | SHOWN_LANGS]
    if unknown:
        for b in unknown:
            print(f"{b.where}: unknown block language `{b.lang}`", file=sys.stderr)
        return 2

    pipe = Path(os.environ.get("PIPE", REPO / "target/release/pipe")).resolve()
    python = Path(os.environ.get("DOCS_PYTHON", REPO / ".venv/bin/python")).absolute()
    if not pipe.is_file():
        print(f"no pipe binary at {pipe}: build it (cargo build --release -p grainpipe-cli) "
              "or set PIPE", file=sys.stderr)
        return 2
    if args.scratch:
        scratch = Path(args.scratch).resolve()
        scratch.mkdir(parents=True, exist_ok=True)
    else:
        scratch = Path(tempfile.mkdtemp(prefix="grainpipe-docs-"))
    for entry in REPO.iterdir():
        link = scratch / entry.name
        if entry.name not in PRIVATE and not link.exists() and not link.is_symlink():
            link.symlink_to(entry)
    s = Session(pipe, python, scratch, args.verbose)
    print(f"scratch directory: {scratch}")

    t0 = time.monotonic()
    failures, ran, skipped = [], 0, 0
    for n, b in enumerate(blocks):
        if b.lang not in RUN_LANGS:
            continue
        if "skip" in b.markers:
            skipped += 1
            print(f"skip {b.where} {b.lang} {b.markers['skip']}")
            continue
        t = time.monotonic()
        ok, msg = True, ""
        for p in s.prerequisites(b):
            ok, msg = s.ensure(p)
            if not ok:
                break
        if ok:
            ok, msg = CHECKS[b.lang](s, b, n)
        ran += 1
        dt = time.monotonic() - t
        print(f"{'ok  ' if ok else 'FAIL'} {b.where} {b.lang} ({dt:.1f} s)", flush=True)
        if not ok or args.verbose:
            print("    " + msg.replace("\n", "\n    ")[-4000:], flush=True)
        if not ok:
            failures.append(b.where)
    total = time.monotonic() - t0
    print(f"\n{ran} blocks run, {len(failures)} failed, {skipped} skipped, {total:.0f} s")
    for f in failures:
        print(f"  FAILED {f}")
    if not args.scratch and not failures:
        shutil.rmtree(scratch, ignore_errors=True)
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
