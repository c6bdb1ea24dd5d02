"""``personalize correlate KINEMATICS... --joint knee_r --out DIR``: correlative joint laws.

Fits the regression law of Pronost et al. (2010, eq. 1) between a joint's
rotations (independent) and its translations (dependent) from per-frame
kinematics (``.mot`` / ``.sto``) with `personalize.correlative_laws.fit_joint_law`
and writes law.json, laws_by_trial.json (``--by-trial``), the seed's Table 1
and Table 2 forms (CSV, Markdown) and deviation.png into DIR, staged
(`write_joint_law`).  Slopes in m/rad, constants in m, in the joint's parent frame.
"""
from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import typer

from lowerlimb.errors import InputError


def _names(text: Optional[str], option: str) -> Optional[list[str]]:
    if text is None:
        return None
    names = [t.strip() for t in text.split(",") if t.strip()]
    if not names:
        raise InputError(option, "empty column list")
    if len(set(names)) != len(names):
        raise InputError(option, "a column is listed twice")
    return names


def _print_summary(fit) -> None:
    from rich.console import Console
    from rich.table import Table as RichTable

    from ..presentation.correlative_tables import format_number as fmt

    law = fit.law
    rt = RichTable(title=f"{fit.joint} law over {len(fit.labels)} trial(s), {law.fit.n_frames} frames")
    for h in ("dependent", "R2", "rms (mm)", "max (mm)", "seed criterion"):
        rt.add_column(h)
    for d, dn in enumerate(law.dependent):
        s = 1e3 if law.dependent_units[d] == "m" else 1.0
        rt.add_row(dn, fmt(law.fit.r2[d], 1, 4), fmt(law.fit.rms[d], s), fmt(law.fit.max_abs[d], s),
                   "yes" if law.fit.seed_criterion[d] else "no")
    Console(stderr=True).print(rt)
    if not law.fit.well_conditioned:
        Console(stderr=True).print(f"[yellow]warning: design condition number {law.fit.condition:.3g}: "
                                   "the rotations are nearly collinear, coefficients poorly determined")


def register(app: typer.Typer) -> None:
    @app.command("correlate")
    def correlate_cmd(
        kinematics: List[Path] = typer.Argument(..., help="Per-frame joint kinematics (.mot/.sto), one file per trial."),
        joint: str = typer.Option("knee_r", "--joint", help="Joint name; picks <joint>_flexion/adduction/rotation and _tx/_ty/_tz columns (side suffix kept last)."),
        out: Path = typer.Option(..., "--out", help="Output folder: law.json, tables, deviation.png."),
        independent: Optional[str] = typer.Option(None, "--independent", help="Comma-separated independent columns (default from --joint)."),
        dependent: Optional[str] = typer.Option(None, "--dependent", help="Comma-separated dependent columns (default from --joint)."),
        rotational: Optional[str] = typer.Option(None, "--rotational", help="Comma-separated rotational columns (default: guessed from names; translations end in _tx/_ty/_tz)."),
        by_trial: bool = typer.Option(False, "--by-trial", help="Also fit one law per trial (sub-motion laws)."),
        folds: int = typer.Option(0, "--folds", help="Held-out error from N contiguous blocks per trial instead of leave-one-trial-out (useful with one trial)."),
        quiet: bool = typer.Option(False, "--quiet", help="No summary table."),
        overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing --out folder whole."),
    ) -> None:
        """Correlative joint law (Pronost 2010): translations as linear functions of the rotations."""
        from ..correlative_laws import fit_joint_law, law_document, write_joint_law
        from ..presentation.correlative_tables import format_number
        from ..outputs import check_output_dir

        ind, dep = _names(independent, "--independent"), _names(dependent, "--dependent")
        rot = _names(rotational, "--rotational")
        check_output_dir(out, inputs=list(kinematics), overwrite=overwrite)
        fit = fit_joint_law(kinematics, joint=joint, independent=ind, dependent=dep, rotational=rot,
                            by_trial=by_trial, folds=folds)
        write_joint_law(fit, out)
        if not quiet:
            _print_summary(fit)
        doc = law_document(fit)["fit"]
        typer.echo(f"wrote law.json (R2 {', '.join(format_number(v, 1, 3) for v in doc['r2'])}; "
                   f"mean deviation {format_number(doc['mean_deviation'], 1e3, 2)} mm) and tables to {out}")
