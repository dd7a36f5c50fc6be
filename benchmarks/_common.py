"""Shared helpers for the benchmark scripts (not part of the installed package).

The scripts are run from the repository root as `python benchmarks/<name>.py`; Python then
puts benchmarks/ on sys.path, so `import _common` finds this file.
"""

from __future__ import annotations

import contextlib
import csv
import json
import math
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import yaml

BENCH_DIR = Path(__file__).resolve().parent
REPO_ROOT = BENCH_DIR.parent
RESULTS_DIR = BENCH_DIR / "results"
SCENARIO_PATH = REPO_ROOT / "configs" / "slab_edge_load.yaml"
REVISION_FILE = ".benchmark-revision"  # in a baseline's extracted folder: the revision it holds


# `stitchplan ARGS` in a fresh process of this Python, from whatever code PYTHONPATH puts first
# (the scripts time a baseline checkout this way too)
STITCHPLAN = [sys.executable, "-c", "import sys; from stitchplan.cli import main; sys.argv[0] = 'stitchplan'; main()"]


def command_line(doc: str | None, flags: Sequence[str] = ()) -> set[str]:
    """A script's flags: `--help` prints its docstring (what it runs, how long) and exits;
    an argument other than `flags` stops it in one line before anything runs."""
    given = sys.argv[1:]
    if "-h" in given or "--help" in given:
        print((doc or "").strip())
        raise SystemExit(0)
    unknown = [argument for argument in given if argument not in flags]
    if unknown:
        expected = " and/or ".join(flags) if flags else "no arguments"
        raise SystemExit(f"{Path(sys.argv[0]).name}: got {' '.join(unknown)}, expected {expected} (--help says "
                         "what it runs)")
    return set(given)


def extract_revision(revision: str, folder: Path, *paths: str) -> Path:
    """The repository at `revision` (only `paths`, default all of it) extracted into
    `folder` with `git archive`, to time a baseline's code beside the working tree's."""
    archive = subprocess.run(["git", "archive", revision, *paths], check=True, capture_output=True,
                             cwd=REPO_ROOT).stdout
    subprocess.run(["tar", "-x", "-C", str(folder)], input=archive, check=True)
    (folder / REVISION_FILE).write_text(revision)  # for command_failure
    return folder


def command_environment(**extra: str) -> dict[str, str]:
    """The environment of a timed command: this one with `extra`, and with Python's bytecode
    cache on (an installed package has its modules compiled; a machine that sets
    PYTHONDONTWRITEBYTECODE would otherwise have every process compile them again)."""
    environment = {key: value for key, value in os.environ.items() if key != "PYTHONDONTWRITEBYTECODE"}
    return {**environment, **extra}


def timed_command(arguments: list[str], summary: Path, cwd: Path, **environment: str) -> tuple[float, dict]:
    """One `stitchplan ARGUMENTS` process (command_environment with `environment`, in `cwd`),
    which writes its summary to `summary`: its wall time (s) and the summary."""
    start = time.perf_counter()
    done = subprocess.run([*STITCHPLAN, *arguments], capture_output=True, cwd=cwd,
                          env=command_environment(**environment))
    if done.returncode != 0:
        raise SystemExit(command_failure(arguments, cwd, done))
    return time.perf_counter() - start, json.loads(summary.read_text())


def command_failure(arguments: Sequence[str], cwd: Path, done: subprocess.CompletedProcess) -> str:
    """One line for a timed command that failed: which code ran it (a baseline's revision,
    extract_revision) and the command's last line on stderr. A baseline older than the scene
    files' keys refuses them (exit 2): its comparison ran on the files of its day, recorded in
    its results file."""
    return failure_line(f"stitchplan {' '.join(map(str, arguments[:2]))}", cwd, done)


def failure_line(what: str, cwd: Path, done: subprocess.CompletedProcess) -> str:
    """`what` with which code ran it (a baseline's revision, extract_revision), its exit code and
    its last line on stderr."""
    marker = Path(cwd) / REVISION_FILE
    code = f"the code of {marker.read_text()}" if marker.exists() else f"the code in {cwd}"
    stderr = done.stderr if isinstance(done.stderr, str) else done.stderr.decode(errors="replace")
    lines = stderr.strip().splitlines()
    return f"{what} with {code} exited {done.returncode}: {lines[-1] if lines else '(nothing on stderr)'}"


def scene_command(name: str, scene: str, options: Sequence[str], folder: Path, cwd: Path,
                  **environment: str) -> tuple[float, dict]:
    """config_command of configs/SCENE.yaml."""
    return config_command(name, REPO_ROOT / "configs" / f"{scene}.yaml", options, folder, cwd, **environment)


def config_command(name: str, config: Path, options: Sequence[str], folder: Path, cwd: Path,
                   **environment: str) -> tuple[float, dict]:
    """timed_command of `stitchplan NAME CONFIG OPTIONS`, its summary (and for `plan` its
    trajectory) written into `folder`: wall time (s) and summary."""
    summary = folder / "summary.json"
    export = ["--export", str(folder / "trajectory.csv")] if name == "plan" else []
    return timed_command([name, str(config), *options, *export, "--summary", str(summary)], summary, cwd,
                         **environment)


@contextlib.contextmanager
def against(revision: str):
    """The code of `revision` extracted (extract_revision) and two scratch folders (before,
    now) for `alternated`, removed afterwards."""
    with tempfile.TemporaryDirectory() as extracted, tempfile.TemporaryDirectory() as scratch:
        folders = (Path(scratch) / "before", Path(scratch) / "now")
        for folder in folders:
            folder.mkdir()
        yield extract_revision(revision, Path(extracted)), folders


# a CSV of whole commands timed by `alternated` (its row after part, scene and what)
ALTERNATED_COLUMNS = ["part", "scene", "what", "before (s)", "now (s)", "ratio", "pairs won now", "same"]


def alternated(name: str, scene: str, options: Sequence[str], baseline: Path, folders: tuple[Path, Path],
               repeats: int, compared: Sequence[str]) -> list:
    """scene_command of the code in `baseline` and of this code, alternating `repeats` times,
    each writing into its own of `folders` (against; "{folder}" in an option is replaced by
    the side's folder): the two medians (s), their ratio (now over before), how many pairs
    this code won, and whether every pair's summaries agree on the `compared` keys and (for
    `plan`) their trajectories byte for byte ("yes" / "no")."""
    before_folder, now_folder = folders
    before, now, same = [], [], True
    for _ in range(repeats):
        seconds, old = scene_command(name, scene, [option.format(folder=before_folder) for option in options],
                                     before_folder, baseline)
        before.append(seconds)
        seconds, new = scene_command(name, scene, [option.format(folder=now_folder) for option in options],
                                     now_folder, REPO_ROOT)
        now.append(seconds)
        same &= all(old.get(key) == new.get(key) for key in compared)
        if name == "plan":
            same &= (before_folder / "trajectory.csv").read_bytes() == (now_folder / "trajectory.csv").read_bytes()
    won = sum(b > n for b, n in zip(before, now))
    return [statistics.median(before), statistics.median(now), statistics.median(now) / statistics.median(before),
            f"{won} of {repeats}", "yes" if same else "no"]


def prepared_tissue_class():
    """PreparedTissue of the code on sys.path, for a `--worker` run with a baseline's code:
    stitchplan.needle.prepared_tissue's, or needle.equilibrium's in a revision from before it
    had a module of its own (8efa343)."""
    try:
        from stitchplan.needle.prepared_tissue import PreparedTissue
    except ModuleNotFoundError:
        from stitchplan.needle.equilibrium import PreparedTissue
    return PreparedTissue


def worker_record(script: str, source: Path, *arguments: str) -> dict:
    """`python SCRIPT --worker ARGUMENTS` in a fresh process with the code in `source` first
    on PYTHONPATH; the JSON record it prints last."""
    environment = {**os.environ, "PYTHONPATH": f"{source}{os.pathsep}{BENCH_DIR}"}
    output = subprocess.run([sys.executable, str(Path(script).resolve()), "--worker", *arguments],
                            capture_output=True, text=True, env=environment, cwd=source)
    if output.returncode != 0:  # a baseline refusing today's scene files, as command_failure says
        command = " ".join([Path(script).name, "--worker", *(argument for argument in arguments if argument)])
        raise SystemExit(failure_line(command, source, output))
    return json.loads(output.stdout.strip().splitlines()[-1])


def verification_replay(scene: str):
    """The shipped trajectory of `scene` (sample_runs/SCENE/trajectory.csv) and the model its
    plan is verified on (half the spacing): (that scenario, the centres as run_insertion's
    center_path). Imports the installed stitchplan: the replay models from
    stitchplan.planning.replay_models, or planning.verification's in a revision from before it
    had a module of its own (9032fde)."""
    from stitchplan.config.scenario import load_scenario
    from stitchplan.io.readers import read_center_path
    from stitchplan.needle.geometry import scenario_needle
    try:
        from stitchplan.planning.replay_models import VERIFICATION_FACTOR, rescaled
    except ModuleNotFoundError:
        from stitchplan.planning.verification import VERIFICATION_FACTOR, rescaled

    refined = rescaled(load_scenario(REPO_ROOT / "configs" / f"{scene}.yaml"), VERIFICATION_FACTOR)
    return refined, read_center_path(REPO_ROOT / "sample_runs" / scene / "trajectory.csv", scenario_needle(refined))


# what the SH 1/2 and 20 mm needle files gained on 2026-12-05 (after 4f42f4e), when they were
# discretized for the needle (results/needle_coupling.md, coupling `shipped`)
ADDED_NEEDLE_KEYS = ("cutting_ramp", "multiplier_length")


def file_at(revision: str, path: str) -> str:
    """The text of the repository's file `path` as it was at git `revision`."""
    return subprocess.run(["git", "show", f"{revision}:{path}"], cwd=REPO_ROOT, check=True,
                          capture_output=True, text=True).stdout


def previous_data(path: Path) -> dict:
    """The data of an SH 1/2 or 20 mm needle file as it was before it was discretized for the
    needle: without its discretization block and ADDED_NEEDLE_KEYS."""
    raw = yaml.safe_load(path.read_text())
    raw.pop("discretization", None)
    for key in ADDED_NEEDLE_KEYS:
        raw["needle"].pop(key, None)
    return raw


def previous_config(scene: str, folder: Path) -> Path:
    """configs/SCENE.yaml as previous_data gives it, written into `folder` (a file the code of
    before 2026-12-05 reads, the keys it lacks left out)."""
    path = folder / f"{scene}_previous.yaml"
    path.write_text(yaml.safe_dump(previous_data(REPO_ROOT / "configs" / f"{scene}.yaml"), sort_keys=False))
    return path


def results_path(name: str) -> Path:
    RESULTS_DIR.mkdir(parents=True, exist_ok=True)
    return RESULTS_DIR / name


def load_slab_scenario():
    """The shipped slab scenario, parsed exactly as `stitchplan deform` parses it."""
    from stitchplan.config.scenario import load_scenario

    return load_scenario(SCENARIO_PATH)


def max_probe_error(values: np.ndarray, reference: np.ndarray) -> float:
    """max_i |u_i - u_ref,i| / max_i |u_ref,i| over the probes (vector norms per probe)."""
    values, reference = np.asarray(values), np.asarray(reference)
    return float(np.linalg.norm(values - reference, axis=1).max()
                 / np.linalg.norm(reference, axis=1).max())


def median_time(function: Callable[[], object], repeats: int,
                number: int | None = None) -> tuple[float, object]:
    """Median over `repeats` of the mean time of `number` back-to-back calls; returns (s, last result).

    With number=None, one untimed call is made first and `number` is chosen so that each
    sample lasts at least ~20 ms (at most 50 calls), which steadies very short timings.
    """
    if number is None:
        start = time.perf_counter()
        function()
        once = time.perf_counter() - start
        number = int(min(50, max(1, math.ceil(0.02 / max(once, 1e-9)))))
    samples = []
    result = None
    for _ in range(repeats):
        start = time.perf_counter()
        for _ in range(number):
            result = function()
        samples.append((time.perf_counter() - start) / number)
    return statistics.median(samples), result


def repeats_for(seconds: float, minimum: int, budget: float = 3.0, maximum: int = 15) -> int:
    """How many runs of a job taking `seconds` fit in `budget` seconds, clipped to [minimum, maximum]."""
    return int(min(maximum, max(minimum, budget // max(seconds, 1e-9))))


def loglog_slope(x: Sequence[float], y: Sequence[float]) -> float:
    """Least-squares slope of log y against log x."""
    return float(np.polyfit(np.log(np.asarray(x, float)), np.log(np.asarray(y, float)), 1)[0])


def fmt(value: object, digits: int = 4) -> str:
    if isinstance(value, (float, np.floating)):
        if value == 0.0:
            return "0"
        if not math.isfinite(value):
            return str(value)
        magnitude = abs(value)
        if magnitude >= 1e5 or magnitude < 1e-3:
            return f"{value:.{digits - 1}e}"
        return f"{value:.{digits}g}"
    return str(value)


def write_csv(path: Path, header: Sequence[str], rows: Sequence[Sequence[object]]) -> None:
    with open(path, "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(header)
        for row in rows:
            writer.writerow([repr(float(v)) if isinstance(v, (float, np.floating)) else v for v in row])


def markdown_table(header: Sequence[str], rows: Sequence[Sequence[object]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(fmt(v) for v in row) + " |" for row in rows]
    return "\n".join(lines)


def write_report(name: str, lines: Sequence[str]) -> None:
    """Write the markdown report results/<name> and print it."""
    text = "\n".join(lines)
    results_path(name).write_text(text)
    print()
    print(text)


def write_results(stem: str, header: Sequence[str], rows: Sequence[Sequence[object]], lines: Sequence[str]) -> None:
    """results/STEM.csv, and results/STEM.md: `lines` (title and text) and the table."""
    write_csv(results_path(f"{stem}.csv"), header, rows)
    write_report(f"{stem}.md", [*lines, "", markdown_table(header, rows)])


def panels_legend(figure, axes, ncol: int, fontsize: int = 8) -> None:
    """One legend for all of a figure's panels (`axes`, an array), below them, each label once:
    no panel's data hidden behind a legend."""
    handles = {}
    for axis in axes.ravel():
        for handle, label in zip(*axis.get_legend_handles_labels()):
            handles.setdefault(label, handle)
    figure.legend(list(handles.values()), list(handles), loc="lower center", ncol=ncol, fontsize=fontsize)


def save_figure(figure, path: Path, rect: tuple[float, float, float, float]) -> None:
    """Lay the figure out within `rect` (room for a legend or title outside it), write it, close it."""
    import matplotlib.pyplot as plt

    figure.tight_layout(rect=rect)
    figure.savefig(path, dpi=110)
    plt.close(figure)


def csv_rows(path: Path) -> list[dict]:
    """A results CSV's rows as dicts of strings (a script's --report rewrites its tables from them)."""
    with path.open() as handle:
        return list(csv.DictReader(handle))


def publish(stem: str, text: str, draw: Callable[[list[dict], Path], None], rows: list[dict]) -> None:
    """results/STEM.md (`text`) and results/STEM.png (`draw(rows, path)`), and the text printed."""
    results_path(f"{stem}.md").write_text(text)
    draw(rows, results_path(f"{stem}.png"))
    print(text)


def machine_note() -> str:
    import numpy
    import scipy

    import stitchplan

    threads = os.environ.get("OPENBLAS_NUM_THREADS") or os.environ.get("OMP_NUM_THREADS") or "default"
    return (f"Python {platform.python_version()}, numpy {numpy.__version__}, scipy {scipy.__version__}, "
            f"stitchplan {stitchplan.__version__}, {os.cpu_count()} CPUs, BLAS threads: {threads}, "
            f"{time.strftime('%Y-%m-%d %H:%M')}")
