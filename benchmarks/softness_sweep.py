"""Where the needle model stops converging: the unplanned exit error's refinement ladder as the
tissue gets softer against the needle's loads.

On the soft scenes the free edge at the needle's entry is drawn into a cusp that sharpens at
every level (benchmarks/exit_components.py, entry_release.py), so their exit error does not
settle. Here two needle scenes, each file as shipped but neo-Hookean, are run at h, h/2, h/4
and h/8 (h the file's spacing; a level after one that stops is not run) with the slab's thickness swept (the forces are totals through it,
so a thinner slab is a softer one against the same needle):

- configs/sh12_100x100.yaml (SH 1/2 needle, friction 0.0602 N/mm, cutting force 0.7 N),
  thickness SH_THICKNESSES mm;
- configs/needle20_entry30.yaml (20 mm needle, friction 0.02 N/mm, cutting force 0.03 N) with
  lambda and mu read as N/cm^2 as configs/thesis/needle20_entry30.yaml reads them (x 0.01),
  thickness NEEDLE20_THICKNESSES mm; and at the thesis's 10 mm with Saint Venant-Kirchhoff,
  the thesis's law.

Each is placed by the needle's line load against the slab's shear stiffness,
(friction + cutting_force / R) / (mu t): the friction per mm of needle and the cutting force
per mm of needle radius over mu t (N/mm each). Reported: the exit errors, their changes per
halving, and the free edge within 3 mm of the entry once the tip has left
(how far its tangent turns: exit_components.entry_edge) at each level.

Writes benchmarks/results/softness_sweep.{csv,md,png}. About 25 minutes (`--report`: only the
table and chart, from the CSV).
Run from the repository root:  python benchmarks/softness_sweep.py
"""

from __future__ import annotations

import os

# single-threaded BLAS, as the `stitchplan` command sets it
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
from dataclasses import replace  # noqa: E402

import _common as common  # noqa: E402
import exit_components  # noqa: E402
from stitchplan.config import load_scenario, with_discretization  # noqa: E402

SH_THICKNESSES = (10.0, 6.0, 4.0, 3.5, 3.0, 2.75, 2.5)
NEEDLE20_THICKNESSES = (100.0, 40.0, 20.0, 10.0, 6.0)
THESIS_UNITS = 0.01  # N/cm^2 in MPa
FACTORS = (1.0, 0.5, 0.25, 0.125)
LEVELS = ("h", "h/2", "h/4", "h/8")
NEO_HOOKEAN, SVK = "neo-hookean", "saint-venant-kirchhoff"
SH, NEEDLE20 = "sh12_100x100", "needle20_entry30 (N/cm^2)"
FIELDS = ("family", "law", "thickness_mm", "load_ratio", "factor", "spacing_mm", "particles", "exit_error_mm",
          "edge_turn_deg", "edge_least_stretch", "seconds", "failure")


def scenario(family: str, thickness: float, law: str):
    """The family's file as shipped with the slab `thickness` mm thick and the law `law`."""
    if family == SH:
        base = load_scenario(common.REPO_ROOT / "configs" / "sh12_100x100.yaml")
        material = replace(base.tissue.material, model=law)
    else:
        base = load_scenario(common.REPO_ROOT / "configs" / "needle20_entry30.yaml")
        material = base.tissue.material
        material = replace(material, model=law, lame_lambda=material.lame_lambda * THESIS_UNITS,
                           lame_mu=material.lame_mu * THESIS_UNITS)
    return replace(base, tissue=replace(base.tissue, thickness=thickness, material=material))


def load_ratio(base) -> float:
    """(friction + cutting_force / R) / (mu t): the needle's line loads over the slab's shear stiffness."""
    needle = base.needle
    return (needle.friction + needle.cutting_force / needle.radius) / (base.tissue.material.lame_mu * base.tissue.thickness)


def run(family: str, thickness: float, law: str, factor: float) -> dict:
    base = scenario(family, thickness, law)
    spacing = base.discretization.spacing * factor
    row = {"family": family, "law": law, "thickness_mm": f"{thickness:g}", "load_ratio": f"{load_ratio(base):.4f}",
           "factor": f"{factor:.4f}", "spacing_mm": f"{spacing:.4f}",
           **exit_components.edge_run(with_discretization(base, spacing=spacing))}
    print(row, flush=True)
    return row


def ladder(family: str, thickness: float, law: str) -> list[dict]:
    """The case's runs at FACTORS, up to the first that stops."""
    rows = []
    for factor in FACTORS:
        rows.append(run(family, thickness, law, factor))
        if rows[-1]["failure"]:
            break
    return rows


def cases() -> list[tuple[str, float, str]]:
    return ([(SH, t, NEO_HOOKEAN) for t in SH_THICKNESSES] + [(NEEDLE20, t, NEO_HOOKEAN) for t in NEEDLE20_THICKNESSES]
            + [(NEEDLE20, 10.0, SVK)])


def ladders(rows: list[dict]) -> list[dict]:
    """Per case: load ratio, exit errors and edge turns at LEVELS (None where the run stopped)."""
    out = []
    for family, thickness, law in cases():
        levels = [next((r for r in rows if r["family"] == family and r["law"] == law
                        and r["thickness_mm"] == f"{thickness:g}" and r["factor"] == f"{f:.4f}"), None)
                  for f in FACTORS]
        out.append({"family": family, "law": law, "thickness": thickness, "ratio": float(levels[0]["load_ratio"]),
                    "errors": [float(r["exit_error_mm"]) if r and r["exit_error_mm"] else None for r in levels],
                    "turns": [float(r["edge_turn_deg"]) if r and r["edge_turn_deg"] else None for r in levels],
                    "failures": [r["failure"] if r else "not run" for r in levels]})
    return out


def change(a: float | None, b: float | None) -> float | None:
    return None if a is None or b is None else 100.0 * (b - a) / a


def table(rows: list[dict]) -> tuple[list[str], list[list]]:
    halvings = [f"{a} -> {b} (%)" for a, b in zip(LEVELS, LEVELS[1:])]
    header = ["scene", "law", "thickness (mm)", "load ratio", *(f"exit error at {level} (mm)" for level in LEVELS),
              *halvings, f"edge turn at {', '.join(LEVELS)} (deg)"]
    body = []
    for case in ladders(rows):
        errors = [f"{e:.5f}" if e is not None else "—" if failure == "not run" else f"stops: {failure[:50]}"
                  for e, failure in zip(case["errors"], case["failures"])]
        turns = " / ".join(f"{t:.1f}" if t is not None else "—" for t in case["turns"])
        changes = [change(a, b) for a, b in zip(case["errors"], case["errors"][1:])]
        body.append([case["family"], case["law"], case["thickness"], case["ratio"], *errors,
                     *(f"{c:+.2f}" if c is not None else "—" for c in changes), turns])
    return header, body


def chart(rows: list[dict], path) -> None:
    """Left: the exit error's change per halving against the load ratio (the coupling's 2 %
    convergence criterion dotted); right: how far the entry's edge turns at each level."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(1, 2, figsize=(12.5, 5.6), squeeze=False)
    changes, turns = axes[0]
    styles = {SH: ("tab:blue", "o"), NEEDLE20: ("tab:orange", "s")}
    every = ladders(rows)
    for family, (color, marker) in styles.items():
        cases_ = [c for c in every if c["family"] == family and c["law"] == NEO_HOOKEAN]
        ratio = [c["ratio"] for c in cases_]
        for index, style in enumerate(("-", "--", ":")):
            label = f"{LEVELS[index]} -> {LEVELS[index + 1]}"
            values = [change(*c["errors"][index:index + 2]) for c in cases_]
            kept = [(x, abs(v)) for x, v in zip(ratio, values) if v is not None]
            if not kept:
                continue
            changes.plot(*zip(*kept), linestyle=style, color=color, marker=marker, label=f"{family}: {label}")
        for level, style in zip(LEVELS, ((0, (1, 3)), ":", "--", "-")):
            kept = [(c["ratio"], c["turns"][LEVELS.index(level)]) for c in cases_
                    if c["turns"][LEVELS.index(level)] is not None]
            turns.plot(*zip(*kept), linestyle=style, color=color, marker=marker, label=f"{family}: {level}")
    changes.axhline(2.0, color="k", lw=0.7, ls=":")
    changes.set(xlabel="(friction + cutting force / R) / (mu t)", ylabel="|change of the exit error| (%)",
                title="The unplanned exit error per halving of the spacing")
    turns.set(xlabel="(friction + cutting force / R) / (mu t)", ylabel="turn of the tangent (deg)",
              title="The free edge within 3 mm of the entry after the exit")
    common.panels_legend(figure, axes, ncol=4)
    common.save_figure(figure, path, rect=(0.0, 0.2, 1.0, 1.0))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--report", action="store_true", help="only rewrite the table and chart from the CSV")
    csv_path = common.results_path("softness_sweep.csv")
    if parser.parse_args().report:
        rows = common.csv_rows(csv_path)
    else:
        rows = [row for case in cases() for row in ladder(*case)]
        common.write_csv(csv_path, FIELDS, [[row[key] for key in FIELDS] for row in rows])
    header, body = table(rows)
    text = "\n".join(["# Where the needle model stops converging",
                      f"Generated by `python benchmarks/softness_sweep.py` ({common.machine_note()}). "
                      "`simulate` at h, h/2, h/4, h/8 (h the file's spacing; none after a level that stops) on configs/sh12_100x100.yaml and on "
                      "configs/needle20_entry30.yaml with lambda, mu read as N/cm^2 (configs/thesis), both "
                      "neo-Hookean (one Saint Venant-Kirchhoff row, the thesis's law), with the slab's thickness "
                      "swept. Load ratio: (friction + cutting force / R) / (mu t). Edge turn: how far the tangent "
                      "of the free edge within 3 mm of the entry turns once the tip has left (0: straight, 180: "
                      "folded back; exit_components.entry_edge). softness_sweep.png charts both against the "
                      "load ratio.", "", common.markdown_table(header, body), ""])
    common.publish("softness_sweep", text, chart, rows)


if __name__ == "__main__":
    main()
