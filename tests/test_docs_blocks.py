"""Every fenced code block of README.md, docs/*.md and benchmarks/README.md is run or checked.

Each block is one test (``test_block[docs/montecarlo.md:15]``), handled by the one entry of
:data:`BLOCKS` whose ``key`` (a piece of text) occurs in it.  The kinds of entry:

* ``run``: executed as written -- ``python`` blocks with this interpreter, ``bash``/``sh``
  blocks with bash (``set -euo pipefail``) -- in a fresh folder holding ``scenarios/``,
  ``examples/`` and links to ``benchmarks/``, ``tests/`` and ``src/``, with ``uimm-jax`` and
  ``python`` on the ``PATH`` meaning this interpreter.  It must exit 0 and write the files
  in ``creates``.  Two things shorten them, both stated here and nowhere hidden:

  - ``scenarios/`` holds **shortened copies** of the shipped scenarios: each lasts
    :data:`SHORT_DURATION` s instead of 100 s, its event times and ``[sweep]`` onsets scaled
    with it (the rule of ``uimm-jax sweep --duration``), so that a 1e6-sample run of the
    docs becomes a 1e4-sample run.  The commands and the code are the docs'; only the
    length of the runs differs.  ``examples/`` is copied as it is.
  - ``subs``: exact text replacements made before running, for blocks whose run counts or
    iterations would take minutes (``--runs 200`` -> ``--runs 8``).  Each must match.
    The sweeps of montecarlo.md and tuning.md's evaluation run batches of 48 runs (3
    cells x 16 runs, or 5 x 8 padded to 48), so that they share the compiled uimm and imm
    kernels (one compile each for the file, through the shared cache below).

  ``drop`` removes leading ``&&``-steps of a one-line command (the venv and ``pip install``
  of the Quick start: the suite runs inside the installed environment).
* ``flags``: benchmark command lines (each benchmark takes minutes): each line is
  ``python benchmarks/SCRIPT.py [FLAGS]``; the script's ``--help`` must exit 0 and name
  every flag of the line.
* ``parse``: command lines that cannot run here (several hosts, Slurm, a GPU) or that
  record an experiment of an hour: every ``uimm-jax`` command of the block (also inside
  ``srun ...`` or ``ssh host '...'``) must parse with the CLI's own parser, flags and
  values; ``reason`` says why it is not run and ``by`` names a test running the same
  path, if any (checked to exist).
* ``covered``: run by another test of the suite, named in ``by`` (checked to exist).
* ``skip``: not run, with the reason (the suite itself).
* ``toml``: parsed; a complete scenario by the scenario parser, a fragment of a shipped
  file must be part of that file (``part_of``), the ``[sweep]`` example merged into a
  scenario and validated (``merge_into``), the ``[filter.est]`` example merged into a
  ``uimm-est`` scenario's ``[filter]`` (``check="filter_est"``), anything else by ``check``.
* ``csv``: loaded by ``load_measurements`` against ``scenarios/paper_sim1_tuned.toml``.
* ``text``: output examples and layouts, not code.  A block must carry a language tag:
  an untagged block fails (tag output as ``text``).

A block that no entry matches fails its test: add an entry (run it if you can).

The blocks that run share a JAX compilation cache (a folder of this test session), so
that a kernel that several blocks compile with the same shapes (the tuning gradient of
docs/tuning.md) is compiled once; it changes no result.

Cost (session 6, ``pytest -rP`` prints each block's CPU time): 98 s of CPU and 131 s wall
for the file on the shared 2-core machine at load 5-6 (128 s of CPU at load 5-11), of
which ``uimm-jax tune`` (tuning.md:10, compiling the gradient) 30 s and the two sweeps of
montecarlo.md:9 23 s; every other block 0.6-10 s.
"""

from __future__ import annotations

import copy
import os
import re
import resource
import shlex
import shutil
import subprocess
import sys
import tomllib
import warnings
from dataclasses import dataclass
from pathlib import Path

import pytest

from uimm_jax import dump_scenario, load_scenario, parse_scenario
from uimm_jax.cli._args import with_duration
from uimm_jax.errors import UIMMWarning
from uimm_jax.plants.registry import ENTRY_POINT_GROUP
from uimm_jax.scenario.measured import load_measurements
from uimm_jax.scenario.sweep import sweep_spec

ROOT = Path(__file__).resolve().parents[1]
DOC_FILES = ("README.md", *sorted(f"docs/{p.name}" for p in (ROOT / "docs").glob("*.md")),
             "benchmarks/README.md")  # fmt: skip
#: The length of the shortened scenario copies (s): 1e4 samples of the paper's 1e-4 s.
SHORT_DURATION = 1.0
#: Wall-clock seconds after which a block counts as hung (generous: the CPU time of the
#: slowest block, the tuning command, is about a minute, and the machine may be shared).
TIMEOUT = 1800


@dataclass(frozen=True)
class Entry:
    """How one block is handled (see the module docstring)."""

    doc: str
    key: str
    kind: str
    subs: tuple[tuple[str, str], ...] = ()
    drop: int = 0
    creates: tuple[str, ...] = ()
    setup: str | None = None
    reason: str = ""
    by: str = ""
    part_of: str = ""
    merge_into: str = ""
    check: str = ""


@dataclass(frozen=True)
class Block:
    doc: str
    line: int
    lang: str
    text: str

    @property
    def id(self) -> str:
        return f"{self.doc}:{self.line}"


def extract_blocks(doc: str) -> list[Block]:
    """The fenced blocks of ``doc`` (also indented ones, inside list items)."""
    blocks, open_at, lang, indent, lines = [], None, "", "", []
    for no, line in enumerate((ROOT / doc).read_text().splitlines(), start=1):
        m = re.match(r"^(\s*)```\s*(\S*)\s*$", line)
        if open_at is None:
            if m:
                open_at, indent, lang, lines = no, m.group(1), m.group(2), []
        elif m and line.strip() == "```":
            blocks.append(Block(doc, open_at, lang, "\n".join(lines) + "\n"))
            open_at = None
        else:
            lines.append(line[len(indent) :] if line.startswith(indent) else line)
    assert open_at is None, f"{doc}:{open_at}: a fenced block is never closed"
    return blocks


ALL_BLOCKS = [b for doc in DOC_FILES for b in extract_blocks(doc)]

BENCH = "benchmark command lines: each benchmark runs for minutes (its own --quick too)"

BLOCKS = (
    # ---------------------------------------------------------------- README.md
    Entry("README.md", "pip install -e . && uimm-jax run", "run", drop=3,
          creates=("out/sim1/summary.json", "out/sim1/timeseries.npz",
                   "out/sim1/mode_probabilities.png", "out/sim1/states.png",
                   "out/sim1/innovation.png")),
    Entry("README.md", "pip install -e '.[test]' && pytest -q -n 2", "skip",
          reason="the suite itself (CI runs this line verbatim, .ci/run)"),
    Entry("README.md", "# 1. A scenario file, end to end.", "run"),
    Entry("README.md", "register_plant(LinearPlant(", "run"),
    Entry("README.md", "src/uimm_jax/", "text"),
    # ---------------------------------------------------------------- docs/measurements.md
    Entry("docs/measurements.md", "uimm-jax run scenarios/paper_sim1_tuned.toml --measurements",
          "run", setup="my_run_csv",
          creates=("out/summary.json", "out/states.png", "out/innovation.png")),
    Entry("docs/measurements.md", "load_measurements(\"my_run.csv\"", "run", setup="my_run_csv"),
    Entry("docs/measurements.md", "t,x_p,v_p,p_h,i_v", "csv"),
    # ---------------------------------------------------------------- docs/model_count.md
    Entry("docs/model_count.md", "bench_model_count.py", "flags", reason=BENCH),
    # ---------------------------------------------------------------- docs/montecarlo.md
    # --runs 16 (the table's 64): both sweeps then run batches of 48 runs, so the second
    # loads the first's compiled uimm and imm kernels from the cache (one compile each).
    Entry("docs/montecarlo.md", "--magnitudes 0.25,0.5,0.75,1 --out out/sim2_magnitudes",
          "run", subs=(("--out out/sweep_paper ", "--runs 16 --out out/sweep_paper "),
                       ("--runs 200", "--runs 8")),
          creates=("out/sweep_paper/results.json", "out/sweep_paper/runs.csv",
                   "out/sim2_magnitudes/results.csv")),
    # runs=16: batches of 48 runs again, the kernels montecarlo.md:9 compiled.
    Entry("docs/montecarlo.md", "write_sweep_outputs(res, \"out/my_sweep\")", "run",
          subs=(("runs=100", "runs=16"),), creates=("out/my_sweep/results.json",)),
    Entry("docs/montecarlo.md", "name = \"sim1\"", "toml",
          merge_into="scenarios/paper_sim1_tuned.toml"),
    Entry("docs/montecarlo.md", "# by hand: process 0 listens", "parse",
          by="tests/studies/test_distributed.py::test_two_processes_equal_one_bit_for_bit",
          reason="two processes on two hosts; the test runs the same two command lines "
          "(--coordinator, --num-processes 2, --process-id 0/1) on 127.0.0.1"),
    Entry("docs/montecarlo.md", "#SBATCH", "parse", reason="a Slurm batch job on 8 GPUs"),
    Entry("docs/montecarlo.md", "srun --nodes=4", "parse", reason="a Slurm job step on 4 hosts"),
    Entry("docs/montecarlo.md", "ssh gpu-a", "parse", reason="two GPU hosts reached by ssh"),
    Entry("docs/montecarlo.md", "error: --resume:", "text"),
    Entry("docs/montecarlo.md", "bench_montecarlo.py --quick", "flags", reason=BENCH),
    Entry("docs/montecarlo.md", "--runs 64 --host-devices 2 --out out/sweep_paper", "parse",
          by="tests/studies/test_distributed.py::test_two_processes_equal_one_bit_for_bit",
          reason="the acceptance run (28 min); the same sweep runs above (montecarlo.md:9), "
          "and the test runs a sweep with --host-devices 2"),
    # ---------------------------------------------------------------- docs/scenarios.md
    Entry("docs/scenarios.md", "dump_scenario(scenario, \"copy.toml\")", "run",
          creates=("copy.toml",)),
    Entry("docs/scenarios.md", "[project.entry-points.", "toml", check="entry_point_group"),
    Entry("docs/scenarios.md", "uimm-jax run examples/plant_module/mass_spring.toml", "run",
          creates=("out/mass_spring/summary.json",)),
    Entry("docs/scenarios.md", "module = \"my_plants\"", "toml",
          part_of="examples/plant_module/mass_spring.toml"),
    Entry("docs/scenarios.md", "[faults.valve_wear]\nKq = 2.95\nKc = 5.175e-9\n", "toml",
          part_of="scenarios/paper_sim1.toml"),
    Entry("docs/scenarios.md", "# Paper simulation 1 (section 4.2, Table 2).", "toml"),
    Entry("docs/scenarios.md", "variant = parse_scenario(d", "run"),
    Entry("docs/scenarios.md", "[filter.est]\npost_floor_means = [0.02, 0.02, 0.002]", "toml",
          part_of="scenarios/paper_sim2_tuned.toml"),
    Entry("docs/scenarios.md", "[filter.est]              # session 10's defaults", "toml",
          merge_into="scenarios/paper_sim2_tuned.toml", check="filter_est"),
    # ---------------------------------------------------------------- docs/faults.md
    Entry("docs/faults.md", "[filter.est]\ndrift_walk = 3.0\nretract_pin = true", "toml",
          merge_into="scenarios/paper_sim2_tuned.toml", check="filter_est"),
    Entry("docs/faults.md", "[filter.est]\ndrift_walk = 3.0   # faults that grow", "toml",
          merge_into="scenarios/paper_sim2_tuned.toml", check="filter_est"),
    Entry("docs/faults.md", "[filter.est]\nend_prior = 1e-6   # faults that stay", "toml",
          merge_into="scenarios/paper_sim2_tuned.toml", check="filter_est"),
    # ---------------------------------------------------------------- docs/tuning.md
    Entry("docs/tuning.md", "--eval-runs 200 --out tuned.toml", "run",
          subs=(("--iters 50", "--iters 2"), ("--train-duration 30", "--train-duration 0.3"),
                ("--eval-runs 200", "--eval-runs 16")),  # 48 runs: montecarlo.md:9's uimm kernel
          creates=("tuned.toml", "tuned.tune.json")),
    Entry("docs/tuning.md", "bench_gradient.py", "flags", reason=BENCH),
    Entry("docs/tuning.md", "tune.fit(problem, batch", "run",
          subs=(("30.0)", "0.3)"), ("iters=50", "iters=2"))),
    Entry("docs/tuning.md", "# Stage 1:", "parse",
          reason="the record of the acceptance experiment (80 min); stage 1 is the command "
          "run above (tuning.md:10), --eval-only and --before-from are run by the test",
          by="tests/studies/test_tuning.py::test_cli_tune_eval_only_evaluates_an_existing_file"),
    # ---------------------------------------------------------------- benchmarks/README.md
    Entry("benchmarks/README.md", "bench_throughput.py --quick", "flags", reason=BENCH),
    Entry("benchmarks/README.md", "bench_throughput.py --json /tmp/thr.json", "flags",
          reason=BENCH),
    Entry("benchmarks/README.md", "bench_vs_reference.py --steps", "flags", reason=BENCH),
    Entry("benchmarks/README.md", "B=1 N=1000000: final declared sets equal", "text"),
    Entry("benchmarks/README.md", "bench_imm_outputs.py --leave-one-out", "flags", reason=BENCH),
    Entry("benchmarks/README.md", "bench_imm_outputs.py --selections", "flags", reason=BENCH),
    Entry("benchmarks/README.md", "bench_imm_outputs.py --post-scan", "flags", reason=BENCH),
    Entry("benchmarks/README.md", "bench_imm_chunks.py", "flags", reason=BENCH),
    Entry("benchmarks/README.md", "bench_montecarlo.py --json mc.json", "flags", reason=BENCH),
    Entry("benchmarks/README.md", "bench_gradient.py --batch 1 --repeat 3", "flags",
          reason=BENCH),
    Entry("benchmarks/README.md", "gpu_check.sh --dry-run", "covered",
          by="tests/studies/test_gpu_path.py::test_gpu_check_dry_run_works_on_the_cpu",
          reason="the --dry-run line; the other two install the CUDA extra and need an "
          "NVIDIA GPU"),
)  # fmt: skip


def entry_for(block: Block) -> list[Entry]:
    return [e for e in BLOCKS if e.doc == block.doc and e.key in block.text]


# ------------------------------------------------------------------------------ set-up


@pytest.fixture(scope="module")
def jax_cache(tmp_path_factory) -> Path:
    """A JAX compilation cache shared by the blocks: a kernel that several blocks compile
    with the same shapes (the sweeps of tuning.md's stages) is compiled once.  The test
    session's own cache (tests/conftest.py) when it has one, so that the blocks also reuse
    what the other tests compiled."""
    session = os.environ.get("JAX_COMPILATION_CACHE_DIR")
    return Path(session) if session else tmp_path_factory.mktemp("jax_cache")


@pytest.fixture(scope="module")
def short_scenarios(tmp_path_factory) -> Path:
    """``scenarios/*.toml`` shortened to :data:`SHORT_DURATION` s (see the module doc)."""
    folder = tmp_path_factory.mktemp("short") / "scenarios"
    folder.mkdir()
    for path in sorted((ROOT / "scenarios").glob("*.toml")):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the paper's probabilities summing to 1.2
            sc = load_scenario(path)
        short = with_duration(sc, min(SHORT_DURATION, float(sc.duration)), "test")
        dump_scenario(short, folder / path.name)
    return folder


def workdir(tmp_path: Path, short: Path) -> Path:
    """A folder laid out like the repository, with the shortened scenarios."""
    work = tmp_path / "work"
    work.mkdir()
    (work / "scenarios").symlink_to(short, target_is_directory=True)
    shutil.copytree(ROOT / "examples", work / "examples",
                    ignore=shutil.ignore_patterns("__pycache__"))  # fmt: skip
    for name in ("benchmarks", "tests", "src"):
        (work / name).symlink_to(ROOT / name, target_is_directory=True)
    shutil.copy(ROOT / "pyproject.toml", work / "pyproject.toml")
    shims = tmp_path / "bin"
    shims.mkdir()
    for name, body in (
        ("python", f'exec {shlex.quote(sys.executable)} "$@"'),
        ("python3", f'exec {shlex.quote(sys.executable)} "$@"'),
        ("uimm-jax", f'exec {shlex.quote(sys.executable)} -m uimm_jax "$@"'),
    ):
        (shims / name).write_text(f"#!/bin/sh\n{body}\n")
        (shims / name).chmod(0o755)
    return work


def block_env(work: Path, cache: Path) -> dict:
    env = {k: v for k, v in os.environ.items() if not k.startswith(("SLURM_", "OMPI_"))}
    env.pop("XLA_FLAGS", None)  # as in a user's shell: the CLI and the library add theirs
    env["PATH"] = f"{work.parent / 'bin'}{os.pathsep}{env.get('PATH', '')}"
    if sys.prefix != sys.base_prefix:
        env["VIRTUAL_ENV"] = sys.prefix  # an activated environment, as the docs assume
    src = str(ROOT / "src")
    env["PYTHONPATH"] = os.pathsep.join(p for p in (src, env.get("PYTHONPATH")) if p)
    env["JAX_PLATFORMS"] = "cpu"
    env["MPLBACKEND"] = "Agg"
    env["JAX_COMPILATION_CACHE_DIR"] = str(cache)
    env["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = "0"
    env["JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES"] = "-1"
    return env


def my_run_csv(work: Path) -> None:
    """``my_run.csv`` of docs/measurements.md: the CSV example of the same page."""
    (block,) = [b for b in ALL_BLOCKS if b.doc == "docs/measurements.md" and b.lang == "csv"]
    (work / "my_run.csv").write_text(block.text)


SETUPS = {"my_run_csv": my_run_csv}


def substituted(block: Block, entry: Entry) -> str:
    text = block.text
    for old, new in entry.subs:
        assert old in text, f"{block.id}: the shortening {old!r} -> {new!r} no longer matches"
        text = text.replace(old, new)
    if entry.drop:
        (line,) = [ln for ln in text.splitlines() if ln.strip()]
        steps = line.split(" && ")
        assert len(steps) > entry.drop, f"{block.id}: expected more than {entry.drop} steps"
        text = " && ".join(steps[entry.drop :]) + "\n"
    return text


def _children_cpu() -> float:
    use = resource.getrusage(resource.RUSAGE_CHILDREN)
    return use.ru_utime + use.ru_stime


def run_block(block: Block, entry: Entry, work: Path, cache: Path) -> None:
    if entry.setup:
        SETUPS[entry.setup](work)
    text = substituted(block, entry)
    if block.lang == "python":
        (work / "block.py").write_text(text)
        cmd = [sys.executable, "block.py"]
    else:
        assert block.lang in ("bash", "sh"), f"{block.id}: run a {block.lang!r} block how?"
        (work / "block.sh").write_text("set -euo pipefail\n" + text)
        cmd = ["bash", "block.sh"]
    cpu0 = _children_cpu()
    res = subprocess.run(cmd, cwd=work, env=block_env(work, cache), capture_output=True, text=True,
                         timeout=TIMEOUT)  # fmt: skip
    print(f"{block.id}: {_children_cpu() - cpu0:.1f} s of CPU")  # shown by pytest -rP
    log = f"{block.id} ran as\n{text}\nstdout:\n{res.stdout[-3000:]}\nstderr:\n{res.stderr[-4000:]}"
    assert res.returncode == 0, log
    assert "Traceback" not in res.stderr, log
    for name in entry.creates:
        assert (work / name).is_file(), f"{block.id}: {name} was not written\n{log}"


def check_flags(block: Block) -> None:
    helps: dict[str, str] = {}
    lines = [ln.split("#", 1)[0].strip() for ln in block.text.splitlines()]
    lines = [ln for ln in lines if ln]
    assert lines, f"{block.id}: no command line"
    for line in lines:
        words = shlex.split(line)
        assert words[0] == "python" and words[1].startswith("benchmarks/"), (block.id, line)
        script = words[1]
        assert (ROOT / script).is_file(), f"{block.id}: {script} does not exist"
        if script not in helps:
            res = subprocess.run([sys.executable, str(ROOT / script), "--help"], cwd=ROOT,
                                 capture_output=True, text=True, timeout=TIMEOUT)  # fmt: skip
            assert res.returncode == 0, res.stderr[-3000:]
            helps[script] = res.stdout
        for flag in (w for w in words[2:] if w.startswith("--")):
            assert re.search(rf"(?<![\w-]){re.escape(flag)}(?![\w-])", helps[script]), (
                f"{block.id}: {script} has no flag {flag} (its --help:\n{helps[script]})"
            )


def uimm_jax_commands(text: str) -> list[list[str]]:
    """The arguments of every ``uimm-jax`` command of a shell block (also ``srun uimm-jax``,
    ``.venv/bin/uimm-jax`` and commands quoted for ``ssh``)."""
    commands: list[list[str]] = []

    def scan(words: list[str]) -> None:
        i = 0
        while i < len(words):
            w = words[i]
            if " " in w:  # a quoted command line (ssh host '...')
                scan(shlex.split(w, comments=True))
            elif w == "uimm-jax" or w.endswith("/uimm-jax"):
                j = i + 1
                while j < len(words) and words[j] not in ("&&", "||", ";", "&", "|"):
                    j += 1
                commands.append(words[i + 1 : j])
                i = j
                continue
            i += 1

    for line in text.replace("\\\n", " ").splitlines():
        scan(shlex.split(line, comments=True))
    return commands


def check_parse(block: Block, entry: Entry) -> None:
    from uimm_jax.cli import build_parser

    commands = uimm_jax_commands(block.text)
    assert commands, f"{block.id}: no uimm-jax command found"
    for argv in commands:
        try:
            build_parser().parse_args(argv)
        except SystemExit:
            cmd = shlex.join(["uimm-jax", *argv])
            raise AssertionError(f"{block.id}: {cmd} does not parse") from None


def contains(big, small) -> bool:
    if isinstance(small, dict):
        return isinstance(big, dict) and all(k in big and contains(big[k], v)
                                             for k, v in small.items())  # fmt: skip
    return big == small


def check_toml(block: Block, entry: Entry) -> None:
    doc = tomllib.loads(block.text)
    if entry.check == "filter_est":  # merged into a uimm-est file's [filter]: every key taken
        base = tomllib.loads((ROOT / entry.merge_into).read_text())
        base["filter"] |= doc["filter"]
        est, given = parse_scenario(base, source=block.id).filter.est, doc["filter"]["est"]
        got = {k: list(v) if isinstance(v := getattr(est, k), tuple) else v for k in given}
        assert est is not None and got == given, est
    elif entry.part_of:
        whole = tomllib.loads((ROOT / entry.part_of).read_text())
        assert contains(whole, doc), f"{block.id}: the snippet differs from {entry.part_of}"
    elif entry.merge_into:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            base = tomllib.loads((ROOT / entry.merge_into).read_text())
            merged = copy.deepcopy(base) | doc
            spec = sweep_spec(parse_scenario(merged, source=block.id))
        assert spec.runs == doc["sweep"]["runs"], spec
    elif entry.check == "entry_point_group":
        assert list(doc["project"]["entry-points"]) == [ENTRY_POINT_GROUP]
    else:
        assert "name" in doc, f"{block.id}: neither a scenario nor a known fragment"
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            parse_scenario(doc, source=block.id)


# ------------------------------------------------------------------------------ tests


def test_every_entry_matches_one_block():
    for e in BLOCKS:
        hits = [b.id for b in ALL_BLOCKS if b.doc == e.doc and e.key in b.text]
        assert len(hits) == 1, f"entry {e.key!r} of {e.doc} matches {hits or 'no block'}"


@pytest.mark.parametrize("block", ALL_BLOCKS, ids=[b.id for b in ALL_BLOCKS])
def test_block(block, tmp_path, short_scenarios, jax_cache):
    assert block.lang, f"{block.id}: give the block a language (text for output examples)"
    entries = entry_for(block)
    assert len(entries) == 1, (
        f"{block.id} ({block.lang}) is handled by {len(entries)} entries of BLOCKS in "
        f"{Path(__file__).name}; add one (run it if you can):\n{block.text}"
    )
    (entry,) = entries
    if entry.kind == "run":
        run_block(block, entry, workdir(tmp_path, short_scenarios), jax_cache)
    elif entry.kind == "flags":
        assert block.lang == "bash", block.id
        check_flags(block)
    elif entry.kind in ("covered", "parse"):
        assert entry.reason
        if entry.by:
            path, name = entry.by.split("::")
            assert f"def {name}(" in (ROOT / path).read_text(), f"{entry.by} does not exist"
        if entry.kind == "parse":
            assert block.lang == "bash", block.id
            check_parse(block, entry)
    elif entry.kind == "skip":
        assert entry.reason
    elif entry.kind == "toml":
        assert block.lang == "toml", block.id
        check_toml(block, entry)
    elif entry.kind == "csv":
        (tmp_path / "data.csv").write_text(block.text)
        sc = load_scenario(ROOT / "scenarios" / "paper_sim1_tuned.toml")
        with pytest.warns(UIMMWarning, match="the run covers the file"):  # a 3-sample file
            data = load_measurements(tmp_path / "data.csv", sc)
        assert data.y.shape[1] == 3
    elif entry.kind == "text":
        assert block.lang == "text", f"{block.id}: tag output examples as text"
    else:
        raise AssertionError(f"unknown kind {entry.kind!r}")
