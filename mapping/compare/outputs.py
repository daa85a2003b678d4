"""The comparison's files besides the method folders: the table (CSV, text, ``compare.json``), the figures, the
meshes rendered side by side and the HTML report (the layout: :mod:`mapping.compare.results`)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from mapping.compare.methods import EC_SUFFIX
from mapping.compare.results import MARKER, CompareResult, colour_map_row
from mapping.export import display_colours_uint8
from radiometry.fileio import atomic_write_json, atomic_write_text
from radiometry.tables import csv_text


def write_outputs(result: CompareResult, dataset, scene, *, views: int, render_width: int, title: str | None,
                  report_sections) -> None:
    """The table (``compare.csv``, ``compare.txt``), the figures, the renders and ``report.html`` of a finished
    comparison into ``result.output``, their paths into ``result.files``."""
    from mapping.plots import save_histogram_figure
    from mapping.report import (ReportFigure, ReportSection, ReportTable, run_sections, save_bar_chart,
                                true_exposures_of, write_html_report)

    out = result.output
    rows = result.table()
    files = result.files
    files["csv"] = atomic_write_text(out / "compare.csv", csv_text(rows, result.columns))
    files["txt"] = atomic_write_text(out / "compare.txt", result.table_text() + "\n")
    held_out = [r for r in result.results if r.run.holdout is not None]
    if held_out:
        lines: list[str] = []   # one header, then every method's rows
        for r in held_out:
            text = r.run.holdout.csv(r.method.name).splitlines(keepends=True)
            lines += text[1:] if lines else text
        files["holdout"] = atomic_write_text(out / "holdout.csv", "".join(lines))
    histograms = {r.method.label: r.run.histogram for r in result.results if r.run.histogram.total}
    figures = []
    if histograms:
        save_histogram_figure(out / "histograms.png", histograms,
                              title="colour disagreement (L1, map vs new sample), normalised")
        files["histograms"] = out / "histograms.png"
        figures.append(ReportFigure(out / "histograms.png",
                                    "Normalised histograms of the L1 distance between the map's colour and each new "
                                    "sample before it is averaged in (the paper's Fig. 9); triangles on the top edge: means."))
    errors = {r.method.name: r.colour_error.mean for r in result.results if r.colour_error is not None}
    if errors:
        files["colour_error"] = save_bar_chart(out / "colour_error.png", errors,
                                               ylabel="mean |error| (8-bit levels)",
                                               title="mesh colour vs true radiance (after a global scale per channel)")
    if views > 0:
        grid = _render_views(result, dataset, scene, views=views, render_width=render_width)
        if grid is not None:
            files["renders"] = grid
    result.files = files

    # ---- the report
    p = result.parameters
    intro = [f"Sequence: {getattr(dataset, 'name', '') or '?'} ({p['frames']} frames, {p['width']}x{p['height']}); "
             f"backend {p['backend']}, voxel size {p['voxel_size']:g} m; poses: {result.pose_source}; every "
             "method fused the same frames at identical poses.",
             "L1: distance between the map's colour and each incoming sample just before it is averaged in, in 8-bit "
             "display levels summed over R, G, B (lower = more coherent colours). Colour err: mean absolute error "
             "per channel (8-bit levels) of the mesh colours against the true radiance after one global scale per "
             "channel (simulated sequences only).",
             "Brightness: " + ("each vignetting model is rescaled to a per-channel image mean of 1, so all methods "
                               "display at the raw images' average brightness and only the shape of the correction "
                               "differs." if p["brightness"] == "mean" else
                               "vignetting models as calibrated (V = 1 at the optical centre).")]
    sections = list(report_sections(result) if callable(report_sections) else report_sections)
    ranking = result.ranking()
    means = {r["method"]: r["L1 mean"] for r in rows}
    notes = [f"Ranking by L1 mean (best first): {', '.join(ranking)}."]
    if len(ranking) > 1 and math.isfinite(means[ranking[0]]) and math.isfinite(means[ranking[1]]):
        gap = means[ranking[1]] - means[ranking[0]]
        if gap < 0.01 * means[ranking[0]]:
            notes.append(f"{ranking[0]} leads {ranking[1]} by only {gap:.3f} levels ({100 * gap / means[ranking[0]]:.2f} "
                         "% of the mean): the L1 mean reacts to small errors of a correction only at second order, so "
                         "a gap this small says that both correct about equally well for this sequence"
                         + (" (the colour error against the truth is the finer measure)." if scene is not None else "."))
    if result.ate is not None:
        notes.append(f"ATE of the shared ICP trajectory: {100 * result.ate.rmse:.2f} cm RMSE over {result.ate.pairs} "
                     "frames.")
    summary = ReportSection("Results", notes,
                            tables=[ReportTable("", [_rounded(r) for r in rows], result.columns)], figures=figures)
    sections.append(summary)
    if held_out:
        sections.append(_holdout_section(held_out, p["holdout_every"]))
    colour_mapped = [r for r in result.results if r.run.colour_map is not None]
    if colour_mapped:
        sections.append(_colour_map_section(colour_mapped))
    if "colour_error" in files:
        sections.append(ReportSection("Colour against ground truth", [
            "Mean absolute error of every mesh vertex's colour against the true radiance of the surface it lies on, "
            "after one global scale per channel, in 8-bit display levels."],
            figures=[ReportFigure(files["colour_error"], "Mesh colour error per method")]))
    if "renders" in files:
        sections.append(ReportSection("The maps side by side", [
            "Each method's mesh ray cast on the CPU (Open3D RaycastingScene) from the same viewpoints of the "
            "trajectory; pixel colours are the vertex colours (display levels) interpolated with the hit "
            "triangle's barycentric coordinates, without shading. "
            + ("The last row is the simulated scene's true radiance (display scale of the LUT run)."
               if scene is not None else "")],
            figures=[ReportFigure(files["renders"], "Meshes from the same viewpoints (columns) per method (rows)")]))
    per_run, run_files = run_sections(out, {r.method.label: r.folder for r in result.results},
                                      ground_truth=dataset.ground_truth(), true_exposures=true_exposures_of(dataset))
    sections += per_run
    files.update(run_files)
    links = []
    for r in result.results:
        for kind in ("mesh_ply", "mesh_glb", "surfels"):
            if kind in r.files:
                links.append((f"{r.method.name}: {Path(r.files[kind]).name}", str(r.files[kind])))
        links.append((f"{r.method.name}: metrics.json", str(r.folder / "metrics.json")))
        if r.run.colour_map is not None:
            links += [(f"{r.method.name}: {name}", str(r.folder / name))
                      for name in ("mesh_colourmap.ply", "colour_map.json") if (r.folder / name).is_file()]
    links += [("table (CSV)", str(files["csv"])), ("table (JSON)", str(out / MARKER))]
    files_text = ("PLY meshes (display colours, sRGB-encoded) open as they are in MeshLab, Blender, Open3D and "
                  "trimesh; --formats adds GLB (three.js), OBJ and mesh_colours.npz (map-unit colours). "
                  "docs/outputs.md: which file for which tool.")
    sections.append(ReportSection("Files", [files_text], links=links))
    files["report"] = write_html_report(out / "report.html", title=title or "radiomap: comparison of corrections",
                                        sections=sections, intro=intro)


def _holdout_section(held_out, every: int):
    """The report's section on the withheld frames: how they judge each map, and the table beside the histogram."""
    from mapping.report import ReportSection, ReportTable

    settings = held_out[0].run.holdout.settings
    rows = [{"method": r.method.name, "frames judged": len(r.run.holdout.evaluated),
             "frames withheld": len(r.run.holdout.frames), "pixels": r.run.holdout.pixels,
             "PSNR dB": r.run.holdout.psnr, "L1": r.run.holdout.l1, "histogram L1 mean": r.run.histogram.stats()["mean"]}
            for r in held_out]
    text = [f"One frame in {every} was withheld from fusion (tracked, never fused, never in the histogram). Each "
            "method's final map is rendered at those frames' poses; the frame's exposure is fitted per channel against "
            "the render (median of observed / rendered in the method's map units: irradiance f^-1(I)/V for the "
            "corrected maps, levels for the raw one, so no method gets a freer exposure model than the others) and the "
            "render goes back through the camera model (f(k V(x) E), or k times the level) to predict the 8-bit image.",
            f"Judged pixels: a rendered surface; observed levels in {settings['dark']}..{settings['saturated'] - 1} in "
            f"every channel; render and frame depth within {settings['depth_tolerance_m']:g} m + "
            f"{100 * settings['depth_relative']:g} % of the depth (occlusion); no depth edge within "
            f"{settings['edge_dilation']} pixels in either. PSNR over all judged channel values pooled (peak 255); L1 "
            "per pixel summed over R, G, B (the histogram's distance). The map is a low-pass image of the scene, so "
            "part of the residual is blur common to every method: compare methods, not the figures with 0. "
            "Per-frame figures: holdout.csv."]
    return ReportSection("Held-out frames", text, tables=[ReportTable("", [_rounded(r) for r in rows], list(rows[0]))])


def _colour_map_section(results):
    """The report's section on the colour-map stage: per method the check's figures of the plain and the optimised
    mesh, the mesh kept and why, and the stage's time."""
    from mapping.report import ReportSection, ReportTable

    first = results[0].run.colour_map
    rows = [{"method": r.method.name, "check frames": r.run.colour_map.check,
             **{k.removeprefix("cm "): v for k, v in colour_map_row(r.run.colour_map).items()}} for r in results]
    text = [f"Each method's mesh was also colour-map optimised ({first.method}; Zhou & Koltun 2014, Open3D's "
            "optimiser) on its radiometrically corrected keyframes, and the plain and the optimised mesh were rendered "
            "at the check frames and judged as the held-out frames are (PSNR in dB, L1 in levels summed over R, G, B). "
            "The optimised mesh (mesh_colourmap.ply) is kept only when the check does not call it a failure (PSNR not "
            "more than 0.5 dB below the plain mesh's, keyframes moved by at most 10 cm, few vertices black or unseen); "
            "otherwise the plain mesh is kept and 'why' names the failed checks. Check frames withheld from fusion "
            "are a fair judge; fused non-keyframes (runs without --holdout-every) favour the plain mesh. Seconds: the "
            "stage's (mesh extraction, optimisation, check). In full: colour_map.json in each method's folder."]
    return ReportSection("Colour map", text, tables=[ReportTable("", [_rounded(r) for r in rows], list(rows[0]))])


def _rounded(row: dict[str, Any]) -> dict[str, Any]:
    return {k: (round(v, 2) if isinstance(v, float) and math.isfinite(v) else v) for k, v in row.items()}


def _render_views(result: CompareResult, dataset, scene, *, views: int, render_width: int) -> Path | None:
    from mapping.report import MeshRaycaster, pick_viewpoints, render_scene_truth, save_render_grid, scaled_intrinsics

    if len(result.poses) == 0:
        return None
    picks = pick_viewpoints(result.poses, views)
    width = min(int(render_width), int(dataset.width))
    K, w, h = scaled_intrinsics(dataset.K, dataset.width, dataset.height, width)
    fused = [rec.index for rec in result.results[0].run.records if rec.fused]
    viewpoints = [{"pose_index": int(i), "frame": int(fused[i]) if i < len(fused) else None,
                   "timestamp": float(result.stamps[i]), "pose": np.asarray(result.poses[i], np.float64).tolist()}
                  for i in picks]
    columns: dict[str, list[np.ndarray]] = {}
    recorded: list[dict[str, Any]] = []      # per column: the viewpoints (pose indices) its tiles were rendered from

    def render_column(label: str, method: str | None, render_one) -> None:
        columns[label] = [render_one(np.asarray(v["pose"], np.float64)) for v in viewpoints]
        recorded.append({"label": label, "method": method, "views": [v["pose_index"] for v in viewpoints]})

    for r in result.results:
        g = r.geometry
        caster = MeshRaycaster(g.vertices, g.triangles, display_colours_uint8(g.colours, r.colour_model.to_display))
        render_column(r.method.label, r.method.name, lambda pose, caster=caster: caster.render(pose, K, w, h))
    if scene is not None:
        ref = _truth_reference(result)
        if ref is not None:
            model, scale = ref
            render_column("true radiance", None, lambda pose: render_scene_truth(
                scene, pose, K, w, h, lambda L: model.to_display((L * scale).astype(np.float32))))
    path = save_render_grid(result.output / "renders.jpg", columns,
                            row_labels=[f"view {j + 1}" for j in range(len(picks))])
    result.renders = {"file": path.name, "width": int(w), "height": int(h), "K": np.asarray(K).tolist(),
                      "viewpoints": viewpoints, "columns": recorded}
    return path


def _truth_reference(result: CompareResult):
    """(colour model, per-channel scale) used to display the true radiance: the LUT run's if there is one,
    else the run with the smallest colour error."""
    candidates = [r for r in result.results
                  if r.colour_error is not None and r.colour_model.display_exposure() is not None]
    if not candidates:
        return None
    lut = [r for r in candidates if r.method.name.removesuffix(EC_SUFFIX) == "lut"]
    best = lut[0] if lut else min(candidates, key=lambda r: r.colour_error.mean)
    return best.colour_model, np.asarray(best.colour_error.scale, np.float32)


def write_compare_json(result: CompareResult) -> None:
    """``compare.json``: the parameters, the table and ranking, per method its model, histogram, colour error,
    geometry and files, and the renders' viewpoints."""
    doc = {
        "format": "radiomap-compare", "version": 1,
        "parameters": result.parameters,
        "pose_source": result.pose_source, "poses_identical": result.poses_identical,
        "ate": None if result.ate is None else result.ate.to_dict(),
        "seconds": result.seconds,
        "ranking_l1_mean": result.ranking(),
        "columns": result.columns,
        "table": result.table(),
        "methods": [{**r.method.describe(), "folder": r.folder.name,
                     "colour_model": r.colour_model.describe(),
                     "histogram": r.run.histogram.stats(),
                     "colour_error": None if r.colour_error is None else r.colour_error.to_dict(),
                     "geometry": {"kind": r.geometry.kind, "vertices": len(r.geometry),
                                  "triangles": int(r.geometry.triangles.shape[0])},
                     "files": {k: Path(v).relative_to(result.output).as_posix() for k, v in r.files.items()},
                     **({} if r.run.colour_map is None else {"colour_map": r.run.colour_map.to_dict()})}
                    for r in result.results],
        "files": {k: Path(v).name for k, v in result.files.items()},
        "renders": result.renders,
    }
    result.files["json"] = atomic_write_json(result.output / MARKER, doc)
