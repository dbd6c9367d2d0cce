"""Benchmark: accuracy (and time) of every heat-kernel method against a checked reference.

Run by hand from the repository root (prints markdown tables to stdout, progress to stderr, and
writes them to ``bench/results/heat_accuracy.md``)::

    python3 bench/heat_accuracy.py                        # 5K-vertex mesh, dense check at 1K
    python3 bench/heat_accuracy.py --size 1500 --dense-size 300 --repeats 1   # quick check

(Formerly Table 2 of ``bench/bases.py``; ``--size`` was ``--accuracy-size``.) Meshes, operators
and seeds: see ``bench/_bases.py``.

- Dense check (``--dense-size`` mesh, 10 seeds, relative times 1e-5 ... 3e-2): the reference
  ``heat_kernels(..., method='rational', tol=1e-12)`` and the exact kernel from a dense
  ``np.linalg.eigh`` of ``D^-1/2 L D^-1/2`` against the dense
  ``expm(-t B⁻¹L)[:, seeds] / B[seeds, seeds]`` (``scipy.linalg.expm``). Rational passes if it is
  within 1e-9 at every time. The check also warms every operation up.
- Accuracy table (one ``--size`` mesh, 50 seeds x relative times 1e-3, 3e-3, 1e-2, 3e-2): every
  heat method vs the reference; the error of a column (seed, time) is
  ``max|K - K_ref| / max|K_ref|``, reported as max and median over the 200 columns. The
  reference is rational tol 1e-12 if it passed the dense check, else the dense-eigh kernel (one
  call; rational tol 1e-12 then becomes one of the rows). Times are the median of ``--repeats``
  calls (one call if the first exceeded ``--max-repeat-s``); ``t / t_ref`` is the ratio to the
  reference's time in the same run.
"""

from __future__ import annotations

import argparse
import time
from typing import Any

import numpy as np
import scipy.linalg as sla
from _bases import HEAT_TOL, N_SEEDS, SMALL_TIMES, TIMES, column_errors, run_timed, setup, warm_up
from _common import Report, load_note, log, timed, versions
from _meshes import mesh_name

from torchfmap.operators.heat import heat_kernels

REF_TOL = 1e-12
DENSE_LIMIT = 1e-9  # the rational reference must match the dense expm to this
ACCURACY_METHODS: list[tuple[str, str, Any, dict]] = [
    # (label, method, tol, extra kwargs)
    ("krylov", "krylov", 1e-6, {}),
    ("krylov", "krylov", 1e-8, {}),
    ("rational", "rational", 1e-6, {}),
    ("backward_euler (n_steps=1)", "backward_euler", None, {}),
    ("spectral (n_eigen=200)", "spectral", None, {"n_eigen": 200}),
    ("krylov local='auto'", "krylov", 1e-6, {"local": "auto"}),
]


def dense_eigh_kernels(L, B, seeds: np.ndarray, times_abs: np.ndarray) -> np.ndarray:
    """Exact ``(T, V, S)`` delta kernels from a dense symmetric eigendecomposition (lumped ``B``).

    With ``D = diag(B)`` and ``D^{-1/2} L D^{-1/2} = U Λ Uᵀ``:
    ``exp(-tA) D⁻¹ e_p = D^{-1/2} U exp(-tΛ) Uᵀ e_p / sqrt(d_p)``.
    """
    d = B.diagonal()
    s = 1.0 / np.sqrt(d)
    lam, U = np.linalg.eigh(s[:, None] * L.toarray() * s[None, :])
    Us = U[seeds].T * s[seeds]  # (V, S)
    return np.stack([s[:, None] * (U @ (np.exp(-t * lam)[:, None] * Us)) for t in times_abs])


def dense_check(n: int, seed: int) -> tuple[list[dict], bool]:
    """Rational (``REF_TOL``) and dense-eigh kernels vs ``scipy.linalg.expm``.

    Returns the table rows and whether the rational reference passed (``< DENSE_LIMIT`` at every t).
    """
    mesh, L, B, seeds = setup(n, seed, n_seeds=10)
    d = B.diagonal()
    times = np.array(SMALL_TIMES + TIMES)
    log(f"dense check on {mesh_name(n)}: rational tol {REF_TOL:g} and dense eigh vs scipy.linalg.expm")
    t_rat, _, K = timed(
        lambda: heat_kernels((L, B), seeds, times * mesh.area, method="rational", tol=REF_TOL)
    )
    K_eigh = dense_eigh_kernels(L, B, seeds, times * mesh.area)
    A = L.toarray() / d[:, None]
    rows, passed = [], True
    for ti, t in enumerate(times):
        t_dense, _, K_dense = timed(lambda t=t: sla.expm(-t * mesh.area * A)[:, seeds] / d[seeds])
        err = column_errors(K[ti][None], K_dense[None])[0].max()
        err_eigh = column_errors(K_eigh[ti][None], K_dense[None])[0].max()
        passed &= bool(err < DENSE_LIMIT)
        rows.append(
            {
                "mesh": mesh_name(n),
                "V": n,
                "seeds": len(seeds),
                "t (rel.)": f"{t:g}",
                f"rational tol={REF_TOL:g}: max col. rel. err": float(err),
                f"< {DENSE_LIMIT:g}": "yes" if err < DENSE_LIMIT else "**NO**",
                "dense eigh: max col. rel. err": float(err_eigh),
                "expm [s]": t_dense,
                "rational, all t [s]": t_rat if ti == 0 else "",
            }
        )
    return rows, passed


def reference(L, B, seeds, times, args, rational_ok: bool) -> tuple[str, float, np.ndarray]:
    """``(label, seconds, K_ref)``: rational tol ``REF_TOL`` if it passed the dense check, else dense eigh."""
    if rational_ok:
        label = f"rational tol {REF_TOL:g}"
        fn = lambda: heat_kernels((L, B), seeds, times, method="rational", tol=REF_TOL)  # noqa: E731
        t_ref, _, K_ref = timed(fn, args.repeats, max_repeat_s=args.max_repeat_s)
    else:
        label = "dense eigh (np.linalg.eigh of D^-1/2 L D^-1/2)"
        log(f"  rational tol {REF_TOL:g} failed the dense check; reference: {label} (one call)")
        t_ref, _, K_ref = timed(lambda: dense_eigh_kernels(L, B, seeds, times))
    log(f"  reference: {label}")
    return label, t_ref, K_ref


def method_row(label: str, method: str, tol, extra: dict, ctx: dict, args) -> dict[str, Any]:
    """One row of the accuracy table: time, column errors vs ``ctx['K_ref']``, worst column."""
    log(f"  {label} tol={tol}")
    kw = dict(extra)
    if kw.get("local"):
        kw["vertices"] = ctx["mesh"].vertices
    tol_used = tol if tol is not None else HEAT_TOL
    fn = lambda: heat_kernels(ctx["ops"], ctx["seeds"], ctx["times"], method=method, tol=tol_used, **kw)  # noqa: E731
    t, K = run_timed(label, fn, args.repeats, args.max_repeat_s)
    row: dict[str, Any] = {"method": label, "tol": f"{tol:g}" if tol is not None else "n/a", "time [s]": t}
    row["t / t_ref"] = t / ctx["t_ref"] if isinstance(t, float) else "n/a"
    if K is not None:
        err = column_errors(K, ctx["K_ref"])
        row["max col. rel. err"] = float(err.max())
        row["median col. rel. err"] = float(np.median(err))
        row["max err ≤ tol"] = "n/a" if tol is None else ("yes" if err.max() <= tol else "**NO**")
        ti, si = np.unravel_index(int(np.argmax(err)), err.shape)
        row["worst column (t rel., seed)"] = f"{TIMES[ti]:g}, {int(ctx['seeds'][si])}"
    return row


def bench_accuracy(args, rational_ok: bool) -> tuple[list[dict], str]:
    """The accuracy table on one ``--size`` mesh, and the label of its reference."""
    log(f"accuracy on {mesh_name(args.size)}")
    mesh, L, B, seeds = setup(args.size, args.seed)
    times = np.array(TIMES) * mesh.area
    label, t_ref, K_ref = reference(L, B, seeds, times, args, rational_ok)
    methods = list(ACCURACY_METHODS)
    if not rational_ok:
        methods.insert(0, ("rational", "rational", REF_TOL, {}))
    ctx = {"mesh": mesh, "ops": (L, B), "seeds": seeds, "times": times, "K_ref": K_ref, "t_ref": t_ref}
    ref_tol = f"{REF_TOL:g}" if rational_ok else "n/a"
    rows: list[dict[str, Any]] = [{"method": f"{label} (reference)", "tol": ref_tol, "time [s]": t_ref}]
    rows[0]["t / t_ref"] = 1.0
    for col in ("max col. rel. err", "median col. rel. err", "max err ≤ tol", "worst column (t rel., seed)"):
        rows[0][col] = "—"
    rows += [method_row(*m, ctx, args) for m in methods]
    return rows, label


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--size", type=int, default=5000, help="mesh size of the accuracy table")
    parser.add_argument("--dense-size", type=int, default=1000, help="mesh size of the dense expm check")
    parser.add_argument("--repeats", type=int, default=3, help="timed repeats (median)")
    parser.add_argument("--max-repeat-s", type=float, default=30.0, help="no repeats if a call takes longer")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    start = time.perf_counter()
    check_rows, rational_ok = dense_check(args.dense_size, args.seed)
    warm_up(args.dense_size, args.seed)
    acc_rows, ref_label = bench_accuracy(args, rational_ok)
    log(f"done in {time.perf_counter() - start:.0f} s")
    out = Report("heat_accuracy")
    out.add(f"## Heat kernels: accuracy vs a checked reference ({versions('scipy')}; {load_note()} at end)")
    out.table(
        "Dense check of the references vs expm(-t B⁻¹L)[:, seeds] / B[seeds, seeds]",
        check_rows,
        note=f"rational: heat_kernels(method='rational', tol={REF_TOL:g}); dense eigh: the exact kernels "
        "from np.linalg.eigh of D^-1/2 L D^-1/2 (D = diag B). Errors: max over seeds of max|K - K_expm| / "
        f"max|K_expm|. The accuracy table uses rational tol {REF_TOL:g} as its reference only if it "
        "passes here at every t, else dense eigh.",
    )
    out.table(
        f"Accuracy on {mesh_name(args.size)}: heat_kernels (delta kernel), {N_SEEDS} seeds x "
        f"{len(TIMES)} times, vs {ref_label}",
        acc_rows,
        note="Column error = max_v |K - K_ref| / max_v |K_ref| for one (seed, time); max / median over the "
        f"{N_SEEDS * len(TIMES)} columns. krylov's tol is a relative B-norm convergence test, not this "
        "max-norm error. Median of `--repeats` calls; t / t_ref: ratio to the reference's time.",
    )
    out.save()


if __name__ == "__main__":
    main()
