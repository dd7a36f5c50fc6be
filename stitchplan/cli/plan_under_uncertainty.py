"""`plan --uncertainty`: its options, and the robust plan over the uncertainty file's
parameter distributions (stitchplan.uncertainty.robust) with its outputs and lines."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from ..allocator import pause_collection, resume_collection
from .guards import guard_plan_under_uncertainty
from .options import check_command_outputs, echo_events, echo_notes, naming_option


def check_uncertainty_options(uncertainty_path: Optional[Path], compare: bool, only_with_it: dict) -> None:
    """Refuse the options `only_with_it` ({option: value}, None: not given) without
    --uncertainty, and --no-compare with it."""
    from ..errors import InputError

    if uncertainty_path is None:
        for option, value in only_with_it.items():
            if value is not None:
                raise InputError(f"{option}: got {value}, expected it only with --uncertainty FILE")
    elif not compare:
        raise InputError("--no-compare: got it with --uncertainty FILE, whose report compares the unplanned, nominal "
                         "and robust exits over the samples; expected it without --uncertainty")


def run_plan_under_uncertainty(scenario_path: Path, scenario, uncertainty_path: Path, executor, auto_note, limits,
                               verify: bool, names: dict, export: Path, out, summary, plot, uncertainty_plot,
                               provenance: dict, quiet: bool, accuracy: float | None = None, **options) -> None:
    """plan --uncertainty: the robust plan over the file's parameter distributions, its
    sampled runs on the executor (stitchplan.uncertainty.robust); with `verify` the plans aimed
    for the refined model and the exported one replayed on it at the scenario's values. With
    `auto_note` (the discretization chosen for the scenario's `accuracy`) its notes come
    first, as `plan`'s do."""
    pause_collection()  # again, for the imports of the uncertainty's modules (stitchplan/allocator.py)
    from ..config.uncertainty import load_uncertainty
    from ..io import reports
    from ..io.progress import progress_bar
    from ..io.uncertainty_reports import uncertainty_lines
    from ..uncertainty.robust import check_exported_plan, check_inputs, plan_under_uncertainty, planned_tasks
    from .runs import put_accuracy_notes_first

    resume_collection()
    with naming_option("--uncertainty", uncertainty_path):
        uncertainty = load_uncertainty(uncertainty_path)
    check_command_outputs({"--export": export, "--out": out, "--summary": summary, "--plot": plot,
                           "--uncertainty-plot": uncertainty_plot},
                          {"--uncertainty": uncertainty_path, "from_calibration": uncertainty.calibration},
                          out_format="HDF5")
    with naming_option("--uncertainty", uncertainty_path):  # its lines against the scenario's values too
        check_inputs(uncertainty, scenario, scenario_path)
    # the files the distributions came from, as the scenario's is recorded (their resolved
    # stds and correlations are the summary's uncertainty.distributions); the file's SHA-256 of the
    # bytes parsed, which a pipe gives once
    provenance.update(uncertainty_file=str(uncertainty_path), uncertainty_file_sha256=uncertainty.sha256)
    if uncertainty.calibration is not None:
        provenance.update(calibration_file=uncertainty.calibration,
                          calibration_file_sha256=uncertainty.calibration_sha256)
    tasks = planned_tasks(uncertainty)
    guard_plan_under_uncertainty(scenario_path, limits, names, scenario, verify, tasks, executor.workers,
                                 options.get("linear_solver"))
    with executor, progress_bar("plans and sampled runs", tasks + 2) as advance:
        result = plan_under_uncertainty(scenario, uncertainty, executor, verify=verify,
                                        on_run=lambda description: advance(description=description), **options)
    plan = check_exported_plan(scenario, result, verify, **options)
    put_accuracy_notes_first(plan.planned.events, auto_note, accuracy, plan.estimate)
    reports.write_plan_outputs(plan, export=export, out=out, summary=summary, plot=plot, provenance=provenance,
                               uncertainty=result, uncertainty_plot=uncertainty_plot)
    typer.echo(reports.plan_line(plan, export))
    for line in uncertainty_lines(result):
        typer.echo(line)
    echo_notes(result.notes, quiet)
    echo_events(plan.planned.events, quiet)
