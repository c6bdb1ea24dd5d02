"""``personalize demo [--out DIR]``: the main job on a built-in phantom, errors against truth."""
from __future__ import annotations

from pathlib import Path

import typer


def render_summary(summary: dict, console) -> None:
    """Print the demo's error tables (`personalize.evaluation.demo.run_demo`'s summary) with rich."""
    from rich.table import Table

    t = Table(title=f"Bone surfaces from a {summary['voxel_mm'][0]:g} mm label volume vs exact phantom surfaces")
    for col in ("bone", "mean |d| (mm)", "max |d| (mm)", "volume error (%)"):
        t.add_column(col, justify="right" if col != "bone" else "left")
    for b, r in summary["surfaces"].items():
        t.add_row(b, f"{r['mean_abs_distance_mm']:.3f}", f"{r['max_distance_mm']:.2f}", f"{r['volume_error_pct']:+.2f}")
    console.print(t)
    p = summary.get("pipeline")
    if p:
        e = Table(title="Joint estimates vs phantom truth (worst side; static-trial lab frame)")
        for col in ("quantity", "MRI only", "motion only", "fused"):
            e.add_column(col, justify="right" if col != "quantity" else "left")
        for k, v in p["errors"].items():
            e.add_row(k, *(f"{v[s]:.2f}" for s in ("mri", "motion", "fused")))
        console.print(e)
        console.print(f"personalised model: IK marker RMS {p['ik_rms_mm']:.2f} mm (worst trial mean)")


def register(app: typer.Typer) -> None:
    @app.command()
    def demo(
        out: Path = typer.Option(Path("demo_out"), "--out", help="Output folder."),
        seed: int = typer.Option(0, "--seed", help="Phantom seed."),
        voxel: float = typer.Option(1.0, "--voxel", help="Isotropic voxel size of the phantom MRI, mm."),
        quick: bool = typer.Option(False, "--quick", help="Short motion trials (faster)."),
        pipeline: bool = typer.Option(True, "--pipeline/--no-pipeline", help="Run the MRI + motion pipeline on the phantom."),
        overwrite: bool = typer.Option(False, "--overwrite", help="Replace a non-empty --out that is not an earlier demo."),
    ) -> None:
        """Run the pipeline on a built-in phantom subject and print its errors against the known truth."""
        from rich.console import Console

        from personalize.evaluation.demo import run_demo
        from personalize.progress import StepProgress

        console = Console()
        # the phantom's 17 labels rasterised and 16 bones meshed, 16 surfaces extracted; the pipeline adds the motion
        # trials and its own ~50 steps (an estimate: the count grows if the work outruns it)
        with StepProgress("demo", 110 if pipeline else 52, Console(stderr=True)) as prog:
            summary = run_demo(out, seed=seed, voxel_mm=voxel, progress=prog, pipeline=pipeline, short=quick,
                               overwrite=overwrite)
        render_summary(summary, console)
        console.print(f"results in {out}/ (demo.json, subject/" + (", model/: model.osim, report.html)" if pipeline else ")"))
