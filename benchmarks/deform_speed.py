"""Cost of the pieces of `stitchplan deform` against the number of particles.

For each particle spacing on configs/slab_edge_load.yaml (dilation 2, default quadrature):

  (a) RK shape functions + gradients at the quadrature points (shape_functions.rk_shape_functions)
      and the whole discretization (discretization.model_for_scenario -> build_tissue_model)
  (b) one tangent assembly (assembly.Assembler.update + tangent_matrix) and one matrix-free
      tangent product (Assembler.tangent_product)
  (c) one sparse direct linear solve (solver.factorize + factor.solve)
  (d) the whole 10-load-step deform (DeformResult.wall_seconds)

(a)-(c) are evaluated at the converged final state of (d) and timed as the median of several
repetitions; (d) is the median of a few full runs. The log-log slope of assembly time against
particles is fitted and reported (linear scaling means slope ~1).

Writes benchmarks/results/deform_speed.{csv,md,png} and prints the table.
Run from the repository root:  python benchmarks/deform_speed.py
"""

from __future__ import annotations

import os

# single-threaded BLAS, as the `stitchplan` command sets it (and for both codes compared):
# the numerics are sparse and small-dense, and BLAS threads only compete on 2 cores
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import statistics

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

import _common as common  # noqa: E402
from stitchplan.tissue.assembly import Assembler  # noqa: E402
from stitchplan.config.scenario import with_discretization  # noqa: E402
from stitchplan.tissue.deform import external_forces, run_deform, to_free  # noqa: E402
from stitchplan.tissue.model import model_for_scenario  # noqa: E402
from stitchplan.tissue.shape_functions import rk_shape_functions  # noqa: E402
from stitchplan.tissue.factorization import factorize  # noqa: E402

SPACINGS = (5.0, 4.0, 3.0, 2.5, 2.0, 1.5, 1.0)
DILATION = 2.0

COLUMNS = {  # key: (csv column, markdown heading)
    "shape": ("shape_functions_s", "(a) RK shape fns at qp (s)"),
    "model": ("build_tissue_model_s", "(a) whole discretization (s)"),
    "update": ("assembler_update_s", "(b) Assembler.update (s)"),
    "tangent": ("tangent_matrix_s", "(b) tangent_matrix after update (s)"),
    "assembly": ("tangent_assembly_s", "(b) assembly = update + tangent_matrix (s)"),
    "product": ("tangent_product_s", "(b) matrix-free K v (s)"),
    "lu": ("factorize_s", "(c) factorize (s)"),
    "lu_solve": ("lu_solve_s", "(c) LU solve (s)"),
    "direct": ("direct_solve_s", "(c) factorize + solve (s)"),
    "deform": ("deform_wall_s", "(d) 10-step deform (s)"),
}


def measure(spacing: float, base, repeats: int, deform_repeats: int) -> dict:
    scenario = with_discretization(base, spacing=spacing, dilation=DILATION)
    results = [run_deform(scenario)]
    repeats_d = common.repeats_for(results[0].wall_seconds, deform_repeats)
    results += [run_deform(scenario) for _ in range(repeats_d - 1)]
    result = results[-1]
    model = result.model
    row = {
        "spacing": spacing,
        "particles": model.n_particles,
        "quadrature_points": len(model.quadrature_weights),
        "dofs": 2 * model.n_free,
        "gradient_nnz": model.gradient.nnz,
        # work of the sparse product B^T (W B) ~ sum over rows of B of nnz(row)^2; constant per
        # particle if the assembly scales linearly
        "spgemm_work_per_particle": float((np.diff(model.gradient.indptr).astype(float) ** 2).sum()
                                          / model.n_particles),
        "max_row_nnz_gradient": int(np.diff(model.gradient.indptr).max()),
        "deform": statistics.median(r.wall_seconds for r in results),
        "deform_runs": len(results),
        "newton": result.report.iterations,
        "factorizations": result.report.factorizations,
        "krylov": result.report.krylov_iterations,
    }

    # (a) shape functions at the quadrature points, and the whole discretization
    row["shape"], _ = common.median_time(
        lambda: rk_shape_functions(model.quadrature_points, model.particles, model.support,
                                   model.volumes, model.discretization.basis_order, True,
                                   model.search, model.basis_scale), repeats)
    row["model"], _ = common.median_time(lambda: model_for_scenario(scenario), repeats)

    # (b) one tangent assembly at the final state, and the matrix-free product
    assembler = Assembler(model)
    deformation_gradient = model.deformation_gradient(result.coefficients)
    row["update"], _ = common.median_time(lambda: assembler.update(deformation_gradient), repeats)
    row["assembly"], (_, matrix) = common.median_time(
        lambda: (assembler.update(deformation_gradient), assembler.tangent_matrix()), repeats)
    # what tangent_matrix costs right after an update (material tangent, if evaluated lazily,
    # plus the sparse product B^T (W B)); derived so it holds whatever update precomputes
    row["tangent"] = max(row["assembly"] - row["update"], 1e-9)
    row["tangent_nnz"] = matrix.nnz
    vector = np.random.default_rng(0).standard_normal(matrix.shape[0])
    row["product"], _ = common.median_time(lambda: assembler.tangent_product(vector), repeats)

    # (c) one sparse direct solve of K x = f_ext
    rhs = to_free(model, external_forces(model, scenario))
    row["lu"], factor = common.median_time(lambda: factorize(matrix), repeats)
    row["lu_solve"], _ = common.median_time(lambda: factor.solve(rhs), repeats)
    row["direct"], _ = common.median_time(lambda: factorize(matrix).solve(rhs), repeats)
    row["lu_nnz"] = factor.stored_entries
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5, help="repetitions for (a)-(c)")
    parser.add_argument("--deform-repeats", type=int, default=3,
                        help="minimum repetitions for (d); cheap spacings get more (~3 s of runs)")
    args = parser.parse_args()

    base = common.load_slab_scenario()
    run_deform(with_discretization(base, spacing=10.0, dilation=DILATION))  # warm-up, not timed
    rows = []
    for spacing in SPACINGS:
        rows.append(measure(spacing, base, args.repeats, args.deform_repeats))
        r = rows[-1]
        print(f"spacing {spacing:4.2f} mm: {r['particles']:6d} particles, assembly "
              f"{r['assembly']:.4f} s, deform {r['deform']:.3f} s", flush=True)

    particles = [r["particles"] for r in rows]
    slopes = {key: common.loglog_slope(particles, [r[key] for r in rows]) for key in COLUMNS}
    large = rows[-4:]  # the four finest discretizations: least per-call overhead
    slopes_large = {key: common.loglog_slope([r["particles"] for r in large], [r[key] for r in large])
                    for key in COLUMNS}

    extra = ["deform_runs", "quadrature_points", "dofs", "gradient_nnz", "max_row_nnz_gradient",
             "spgemm_work_per_particle", "tangent_nnz", "lu_nnz", "newton", "factorizations", "krylov"]
    header = ["spacing_mm", "particles", *extra, *(COLUMNS[k][0] for k in COLUMNS)]
    common.write_csv(common.results_path("deform_speed.csv"), header,
                     [[r["spacing"], r["particles"], *(r[k] for k in extra), *(r[k] for k in COLUMNS)]
                      for r in rows])

    shown = ["shape", "model", "assembly", "product", "direct", "deform"]
    md_header = ["spacing (mm)", "particles", "dofs", "nnz K", *(COLUMNS[k][1] for k in shown)]
    md_rows = [[r["spacing"], r["particles"], r["dofs"], r["tangent_nnz"], *(r[k] for k in shown)]
               for r in rows]
    md_rows.append(["log-log slope (all)", "", "", "", *(f"{slopes[k]:.2f}" for k in shown)])
    md_rows.append([f"slope ({len(large)} finest)", "", "", "", *(f"{slopes_large[k]:.2f}" for k in shown)])
    table = common.markdown_table(md_header, md_rows)

    detail_keys = ["update", "tangent", "lu", "lu_solve"]
    detail_header = ["spacing (mm)", "particles", *(COLUMNS[k][1] for k in detail_keys),
                     "max nnz in a row of B", "sum nnz(B row)^2 / particle",
                     "Newton its", "factorizations", "PCG its"]
    detail_rows = [[r["spacing"], r["particles"], *(r[k] for k in detail_keys),
                    r["max_row_nnz_gradient"], round(r["spgemm_work_per_particle"]), r["newton"],
                    r["factorizations"], r["krylov"]] for r in rows]
    detail_rows.append(["log-log slope (all)", "", *(f"{slopes[k]:.2f}" for k in detail_keys),
                        "", "", "", "", ""])
    detail = common.markdown_table(detail_header, detail_rows)

    work_slope = common.loglog_slope(particles, [r["spgemm_work_per_particle"] * r["particles"]
                                                 for r in rows])
    summary = (f"Tangent assembly (update + tangent_matrix) time ~ particles^{slopes['assembly']:.2f} "
               f"over all spacings, ^{slopes_large['assembly']:.2f} over the {len(large)} finest "
               f"(1.0 = linear). Whole deform ~ particles^{slopes['deform']:.2f}. The operation "
               f"count of the sparse product B^T (W B), sum nnz(B row)^2, grows like "
               f"particles^{work_slope:.2f} (timer-independent).")
    text = "\n".join([
        "# stitchplan deform: cost of the pieces against problem size",
        "",
        f"configs/slab_edge_load.yaml, dilation {DILATION:g}, 2x2 Gauss per background cell. "
        f"(a)-(c) evaluated at the converged final state, median of {args.repeats} repetitions "
        f"(calls shorter than 20 ms are batched and averaged within each repetition); (d) median "
        f"of {min(r['deform_runs'] for r in rows)}-{max(r['deform_runs'] for r in rows)} full "
        f"runs (`DeformResult.wall_seconds`; more for the cheap spacings), after one untimed "
        f"warm-up run.",
        "",
        table,
        "",
        summary,
        "",
        "Breakdown of (b) and (c), the sparsity of the gradient operator B (4 rows per "
        "quadrature point; the work of the product B^T (W B) in tangent_matrix grows like "
        "sum nnz(row)^2, which would stay constant per particle under linear scaling), and the "
        "solver's work per deform run (PCG preconditioned by one early factorization):",
        "",
        detail,
        "",
        f"Machine: {common.machine_note()}",
        "",
    ])
    common.results_path("deform_speed.md").write_text(text)
    print()
    print(table)
    print()
    print(summary)
    print()
    print(detail)

    figure, axis = plt.subplots(figsize=(6.5, 4.8))
    n = np.array(particles, float)
    for key, marker in zip(shown, "osd^vx"):
        axis.loglog(n, [r[key] for r in rows], marker + "-",
                    label=f"{COLUMNS[key][1].replace(' (s)', '')}  (slope {slopes[key]:.2f})")
    guide = rows[0]["assembly"] * n / n[0]
    axis.loglog(n, guide, "k:", lw=0.8, label="linear reference")
    axis.set_xlabel("particles")
    axis.set_ylabel("seconds")
    axis.set_title("stitchplan deform: cost vs particles (slab_edge_load)")
    axis.grid(True, which="both", alpha=0.3)
    axis.legend(fontsize=7)
    figure.tight_layout()
    figure.savefig(common.results_path("deform_speed.png"), dpi=120)


if __name__ == "__main__":
    main()
