"""The page's plotly figures: a scene's maps (inputs, ground truth, predictions, signed errors,
hover read-outs in mm), its 3D surfaces coloured by error, its row profile, the report's bar
charts with seed spread and the robustness curves. Arrays go in as float32 (plotly stores them
base64-typed); maps above MAX_MAP_PX and surfaces above MAX_SURFACE_PX are strided down."""

from __future__ import annotations

import numpy as np
import plotly.graph_objects as go
import torch
from plotly.colors import qualitative
from plotly.subplots import make_subplots

from odmv.data.subsets import edge_band
from odmv.study.results import Cell
from odmv.study.robustness import nets_scale, off_scale_note, ratio_curves, strength_unit
from odmv.study.scenes import SHADOWED_BIT, Scene
from odmv.study.tables import TITLES
from odmv.training.metrics import HEIGHT_BANDS_MM

MAX_MAP_PX = 128  # longest side of a map (and of the profile's samples)
WRAP = 5  # predictions in a row of maps
MAX_SURFACE_PX = 96  # longest side of a 3D surface: rotation stays smooth in a browser
#: one colour and one marker per series, 24 of each (plotly's Dark24: no two alike)
COLOURS = qualitative.Dark24
MARKERS = (
    "circle", "square", "diamond", "triangle-up", "x", "cross", "triangle-down", "star",
    "pentagon", "hexagon", "triangle-left", "triangle-right",
)  # fmt: skip
LAYOUT = {"template": "none", "margin": {"l": 40, "r": 20, "t": 50, "b": 40}}


def wrapped(label: str, width: int = 30) -> str:
    """A long panel title on two lines (plotly does not wrap)."""
    if len(label) <= width or " " not in label[:width]:
        return label
    cut = label.rfind(" ", 0, width)
    return label[:cut] + "<br>" + label[cut + 1 :]


def style(i: int) -> dict:
    return {"color": COLOURS[i % len(COLOURS)], "symbol": MARKERS[i % len(MARKERS)]}


def stride(shape: tuple[int, ...], longest: int) -> int:
    return max(1, int(np.ceil(max(shape) / longest)))


def heights_mm(truth_mm: np.ndarray) -> tuple[float, np.ndarray]:
    """The base plane (the farthest true depth) and heights above it, as the metrics' bands."""
    plane = float(np.nanmax(truth_mm))
    return plane, plane - truth_mm


LINEAR_BELOW_MM = 0.05  # the error scale is linear below this, logarithmic above
ERROR_TICKS_MM = (0.05, 0.2, 1.0, 5.0, 20.0, 100.0)


def signed_log(err_mm: np.ndarray) -> np.ndarray:
    """The colour of a signed error: linear near 0, logarithmic beyond LINEAR_BELOW_MM, so
    0.05 mm and 10 mm errors both read on one unclipped scale."""
    return (np.sign(err_mm) * np.log10(1 + np.abs(err_mm) / LINEAR_BELOW_MM)).astype(np.float32)


def error_axis(scene: Scene) -> dict:
    """The signed-error colour axis over the scene's largest |error| (no clip), ticks in mm."""
    errs = [np.abs(p - scene.truth_mm) for p in scene.predictions.values()]
    top = max((float(np.nanmax(e)) for e in errs if np.isfinite(e).any()), default=1.0)
    ticks = [t for t in ERROR_TICKS_MM if t <= top * 1.5] or [top]
    if len(ticks) > 3:  # on a long scale 0.05 sits a label's height from 0: one of them
        ticks = ticks[1:]
    values = [-t for t in reversed(ticks)] + [0.0] + list(ticks)
    return {
        "colorscale": "RdBu", "reversescale": True,
        "cmin": float(signed_log(np.float32(-top))), "cmax": float(signed_log(np.float32(top))),
        "colorbar": {"title": "error (mm)", "tickvals": [float(signed_log(np.float32(v)))
                     for v in values], "ticktext": [f"{v:g}" for v in values]},
    }  # fmt: skip


def band_errors(scene: Scene) -> list[tuple[str, list[float]]]:
    """MAE (mm) per prediction: all pixels, each height band, interior and edge pixels
    (odmv.data.subsets.edge_band), shadowed pixels."""
    _, height = heights_mm(scene.truth_mm)
    shadowed = (scene.subsets & SHADOWED_BIT) > 0 if scene.subsets is not None else None
    truth = torch.from_numpy(np.ascontiguousarray(scene.truth_mm, np.float32))[None, None]
    edge = edge_band(truth)[0, 0].numpy()
    bands = [(height >= lo) & (height < hi) for lo, hi in HEIGHT_BANDS_MM.values()]
    bands += [~edge, edge]
    out = []
    for label, pred in scene.predictions.items():
        err = np.abs(pred - scene.truth_mm)
        row = [float(np.nanmean(err))]
        for band in bands:
            band = band & np.isfinite(err)
            row.append(float(err[band].mean()) if band.any() else float("nan"))
        if shadowed is not None:
            sel = shadowed & np.isfinite(err)
            row.append(float(err[sel].mean()) if sel.any() else float("nan"))
        out.append((label, row))
    return out


def scene_maps(scene: Scene) -> go.Figure:
    """Every view's input fringe and the ground truth, then the predictions, WRAP to a row,
    each above its signed error (prediction - truth, mm; :func:`error_axis`). Hover: pixel,
    value, error, truth, and (text the page fills in) the pixel's subset."""
    s = stride(scene.truth_mm.shape, MAX_MAP_PX)
    preds = list(scene.predictions.items())
    top = [(f"input: {v}", "fringe", img) for v, img in scene.fringes.items()]
    top.append(("ground truth (mm)", "depth", scene.truth_mm))
    cols = max(len(top), min(WRAP, len(preds)))
    chunks = [preds[i : i + cols] for i in range(0, len(preds), cols)]
    titles = [t for t, _, _ in top] + [""] * (cols - len(top))
    for chunk in chunks:
        pad = [""] * (cols - len(chunk))
        titles += [wrapped(label) for label, _ in chunk] + pad
        titles += [wrapped(f"error: {label}") for label, _ in chunk] + pad
    n_rows = 1 + 2 * len(chunks)
    fig = make_subplots(
        n_rows, cols, subplot_titles=titles, horizontal_spacing=0.012,
        vertical_spacing=0.06 / max(1, n_rows / 3),
    )  # fmt: skip
    h, w = scene.truth_mm[::s, ::s].shape
    ys, xs = np.arange(h) * s, np.arange(w) * s
    truth = scene.truth_mm[::s, ::s].astype(np.float32)
    subset = {"meta": "subsets"} if scene.subsets is not None else {}
    more = "<br>%{text}" if subset else ""

    def add(row, col, z, axis, template, custom=None, name=""):
        fig.add_trace(
            go.Heatmap(
                z=z.astype(np.float32), x=xs, y=ys, coloraxis=axis, customdata=custom,
                hovertemplate=f"row %{{y}}, col %{{x}}<br>{template}{more}<extra>{name}</extra>",
                **subset,
            ),
            row, col,
        )  # fmt: skip

    for k, (title, kind, img) in enumerate(top):
        if kind == "fringe":
            add(1, k + 1, img[::s, ::s], "coloraxis", "intensity %{z:.3f}", name=title)
        else:
            add(1, k + 1, truth, "coloraxis2", "true depth %{z:.3f} mm", name="ground truth")
    for k, (label, pred) in enumerate(preds):
        row, col = 2 + 2 * (k // cols), k % cols + 1
        p = pred[::s, ::s].astype(np.float32)
        err = (p - truth).astype(np.float32)  # each panel's hover reads it (one channel: size)
        add(row, col, p, "coloraxis2", "depth %{z:.3f} mm<br>error %{customdata:.3f} mm", err,
            label)  # fmt: skip
        add(row + 1, col, signed_log(err), "coloraxis3", "error %{customdata:.3f} mm", err, label)
    finite = scene.truth_mm[np.isfinite(scene.truth_mm)]
    lo, hi = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 1.0)
    bar = {"x": 1.0, "len": 0.9 / 3, "thickness": 14}
    fig.update_layout(
        **LAYOUT, height=215 * n_rows + 60, width=210 * cols + 170,
        coloraxis={"colorscale": "gray", "colorbar": {"title": "intensity", "y": 0.85, **bar}},
        coloraxis2={"colorscale": "Viridis", "reversescale": True, "cmin": lo, "cmax": hi,
                    "colorbar": {"title": "depth (mm)", "y": 0.5, **bar}},
        coloraxis3=error_axis(scene),
    )  # fmt: skip
    fig.layout.coloraxis3.colorbar.update(y=0.15, **bar)
    _pixel_axes(fig, n_rows * cols)
    fig.update_annotations(font_size=10)
    return fig


def depth_maps(scene: Scene) -> go.Figure:
    """A scene without ground truth (a user's capture): its input images and each depth map."""
    s = stride(next(iter(scene.predictions.values())).shape, MAX_MAP_PX)
    panels = [
        (f"input: {v}", img, "coloraxis", "intensity %{z:.3f}") for v, img in scene.fringes.items()
    ]
    panels += [(label, d, "coloraxis2", "depth %{z:.3f} mm") for label, d in
               scene.predictions.items()]  # fmt: skip
    # the inputs on a row, the depth maps on the next (each wrapped at WRAP)
    places = [divmod(k, WRAP) for k in range(len(scene.fringes))]
    first = (len(scene.fringes) + WRAP - 1) // WRAP
    places += [(first + k // WRAP, k % WRAP) for k in range(len(scene.predictions))]
    rows, cols = max(r for r, _ in places) + 1, max(c for _, c in places) + 1
    titles = [""] * rows * cols
    for (r, c), panel in zip(places, panels, strict=True):
        titles[r * cols + c] = wrapped(panel[0], 28)
    fig = make_subplots(rows, cols, subplot_titles=titles, horizontal_spacing=0.02,
                        vertical_spacing=0.12)  # fmt: skip
    for (r, c), (title, img, axis, template) in zip(places, panels, strict=True):
        z = img[::s, ::s].astype(np.float32)
        fig.add_trace(
            go.Heatmap(
                z=z, x=np.arange(z.shape[1]) * s, y=np.arange(z.shape[0]) * s, coloraxis=axis,
                hovertemplate=f"row %{{y}}, col %{{x}}<br>{template}<extra>{title}</extra>",
            ),
            r + 1, c + 1,
        )  # fmt: skip
    bar = {"len": 0.8 / rows, "y": 1 - 0.5 / rows, "thickness": 14}
    fig.update_layout(
        **(LAYOUT | {"margin": {"l": 40, "r": 110, "t": 50, "b": 40}}),
        height=300 * rows + 40, width=max(700, 260 * cols + 200),
        coloraxis={"colorscale": "gray", "colorbar": {"title": "intensity", "x": 1.01, **bar}},
        coloraxis2={"colorscale": "Viridis", "reversescale": True,
                    "colorbar": {"title": "depth<br>(mm)", "x": 1.09, **bar}},
    )  # fmt: skip
    _pixel_axes(fig, rows * cols)
    return fig


def depth_surface(scene: Scene) -> go.Figure:
    """A scene without ground truth in 3D: each prediction's height above its farthest depth,
    coloured by height."""
    fig = go.Figure()
    for k, (label, depth) in enumerate(scene.predictions.items()):
        s = stride(depth.shape, MAX_SURFACE_PX)
        x, y, unit = _lateral(scene, depth[::s, ::s].shape, s)
        height = (np.nanmax(depth) - depth[::s, ::s]).astype(np.float32)
        fig.add_trace(
            go.Surface(
                x=x, y=y, z=height, colorscale="Viridis", name=label, visible=k == 0,
                colorbar={"title": "height (mm)"},
                hovertemplate=f"height %{{z:.3f}} mm<extra>{label}</extra>",
            )
        )  # fmt: skip
    fig.update_layout(**LAYOUT, height=520, scene=_scene_axes(unit, height.shape))
    return fig


def _lateral(scene: Scene, shape: tuple[int, int], s: int):
    """Lateral coordinates of a strided map: mm on the base plane where the rig is known."""
    px = (scene.mm_per_px or 1.0) * s
    x = (np.arange(shape[1]) * px).astype(np.float32)
    y = (np.arange(shape[0]) * px).astype(np.float32)
    return x, y, "mm" if scene.mm_per_px else "px"


def _scene_axes(unit: str, shape: tuple[int, int]) -> dict:
    """3D axes: the height axis stretched (heights are a few mm over a field of tens)."""
    return {
        "xaxis_title": f"x ({unit})", "yaxis_title": f"y ({unit})",
        "zaxis_title": "height (mm)", "aspectmode": "manual",
        "aspectratio": {"x": 1, "y": shape[0] / shape[1], "z": 0.35},
        "zaxis": {"nticks": 4, "tickfont": {"size": 9}},  # a short axis: few labels, apart
        "yaxis": {"autorange": "reversed"},
    }  # fmt: skip


def _pixel_axes(fig: go.Figure, panels: int) -> None:
    """Maps without ticks, row 0 on top, square pixels."""
    fig.update_xaxes(showticklabels=False, showgrid=False, zeroline=False)
    fig.update_yaxes(showticklabels=False, showgrid=False, zeroline=False, autorange="reversed")
    for i in range(1, panels + 1):
        fig.layout[f"yaxis{i if i > 1 else ''}"].scaleanchor = f"x{i if i > 1 else ''}"


def scene_surfaces(scene: Scene) -> go.Figure:
    """Heights above the base plane in 3D: the ground truth (grey) and one prediction at a
    time (a menu picks it), coloured by its signed error on the maps' scale."""
    s = stride(scene.truth_mm.shape, MAX_SURFACE_PX)
    plane, truth_h = heights_mm(scene.truth_mm)
    truth_h = truth_h[::s, ::s].astype(np.float32)
    x, y, unit = _lateral(scene, truth_h.shape, s)
    fig = go.Figure(
        go.Surface(
            x=x, y=y, z=truth_h, colorscale=[[0, "#bbbbbb"], [1, "#bbbbbb"]], showscale=False,
            opacity=0.55, name="ground truth",
            hovertemplate="true height %{z:.3f} mm<extra>ground truth</extra>",
        )
    )  # fmt: skip
    labels = list(scene.predictions)
    axis = error_axis(scene)
    for k, label in enumerate(labels):
        pred = scene.predictions[label][::s, ::s]
        err = (pred - scene.truth_mm[::s, ::s]).astype(np.float32)
        fig.add_trace(
            go.Surface(
                x=x, y=y, z=(plane - pred).astype(np.float32), surfacecolor=signed_log(err),
                customdata=err, name=label, visible=k == 0, **axis,
                hovertemplate="height %{z:.3f} mm<br>error %{customdata:.3f} mm"
                f"<extra>{label}</extra>",
            )
        )  # fmt: skip
    buttons = [
        {"label": label, "method": "update",
         "args": [{"visible": [True] + [j == k for j in range(len(labels))]}]}
        for k, label in enumerate(labels)
    ]  # fmt: skip
    fig.update_layout(
        **LAYOUT,
        height=520,
        updatemenus=[{"buttons": buttons, "x": 0, "y": 1.12, "xanchor": "left"}]
        if len(labels) > 1
        else [],
        scene=_scene_axes(unit, truth_h.shape),
    )
    return fig


def scene_profile(scene: Scene, row: int) -> tuple[go.Figure, list[np.ndarray]]:
    """Depth along one row (the paper's Figs. 5 and 7): the ground truth and every
    prediction; returns the figure and the strided maps the page's row slider reads."""
    s = stride(scene.truth_mm.shape, MAX_MAP_PX)
    maps = [scene.truth_mm[::s, ::s]] + [p[::s, ::s] for p in scene.predictions.values()]
    maps = [m.astype(np.float32) for m in maps]
    x = np.arange(maps[0].shape[1]) * s
    fig = go.Figure()
    for k, (label, m) in enumerate(zip(["ground truth", *scene.predictions], maps, strict=True)):
        line = {"color": "black", "width": 3} if k == 0 else {"color": style(k - 1)["color"]}
        fig.add_trace(
            go.Scatter(
                x=x, y=m[row], name=label, mode="lines+markers" if k else "lines", line=line,
                marker={"symbol": style(k - 1)["symbol"], "size": 5},
                hovertemplate="col %{x}: %{y:.3f} mm",
            )
        )  # fmt: skip
    fig.update_layout(
        **LAYOUT, height=420, title=f"profile along row {row * s}",
        xaxis_title="column (px)", yaxis={"title": "depth (mm)", "autorange": "reversed"},
        legend={"orientation": "h", "y": -0.2},
    )  # fmt: skip
    return fig, maps


def tallest_row(scene: Scene) -> int:
    """The strided row through the scene's highest point: where the nets differ most."""
    s = stride(scene.truth_mm.shape, MAX_MAP_PX)
    t = np.nan_to_num(scene.truth_mm[::s, ::s], nan=np.inf)
    return int(np.unravel_index(np.argmin(t), t.shape)[0])


def table_bars(name: str, cells: list[Cell]) -> go.Figure:
    """A table's test MAE per row, all pixels and shadowed ones: mean bars, the std as error
    bars, and every seed as a dot."""
    fig = go.Figure()
    # a row without a finished run keeps its slot, named so: missing, not zero
    labels = [wrapped(c.label, 24) + ("" if c.runs else "<br>(missing)") for c in cells]
    for k, (sub, text) in enumerate((("", "all pixels"), ("_shadowed", "shadowed pixels"))):
        key = f"test/mae_mm{sub}"
        stats = [c.stat(key) for c in cells]
        fig.add_trace(
            go.Bar(
                x=labels, y=[m for m, _ in stats], name=text, offsetgroup=k,
                marker_color=COLOURS[k],
                error_y={"type": "data", "array": [0 if not np.isfinite(d) else d
                                                   for _, d in stats]},
                hovertemplate="%{x}: %{y:.4f} mm<extra>" + text + "</extra>",
            )
        )  # fmt: skip
        seeds_x, seeds_y, seeds_t = [], [], []
        for c, label in zip(cells, labels, strict=True):
            for r in c.by_seed():
                if key in r.metrics:
                    seeds_x.append(label)
                    seeds_y.append(float(r.metrics[key]))
                    seeds_t.append(f"seed {r.metrics.get('seed', '?')}")
        fig.add_trace(
            go.Scatter(
                x=seeds_x, y=seeds_y, mode="markers", name=f"{text}, each seed",
                offsetgroup=k, text=seeds_t, showlegend=True,
                marker={"color": "black", "size": 6, "symbol": MARKERS[k]},
                hovertemplate="%{x}, %{text}: %{y:.4f} mm<extra></extra>",
            )
        )  # fmt: skip
    fig.update_layout(
        **LAYOUT, title=TITLES[name], barmode="group", height=480, scattermode="group",
        yaxis_title="test MAE (mm), mean ± std over seeds",
        legend={"orientation": "h", "y": 1.0, "yanchor": "bottom", "x": 1, "xanchor": "right"},
    )  # fmt: skip
    return fig


def _nets_scale(fig: go.Figure, curves: dict, row: int, col: int) -> None:
    """A panel in the nets' scale where the classical method would squash them
    (odmv.study.robustness.nets_scale): its curve runs off the top, its peak written there."""
    scale = nets_scale(curves)
    if scale is None:
        return
    fig.update_yaxes(range=[scale[0], scale[1]], row=row, col=col)
    fig.add_annotation(text=off_scale_note(scale[2]), xref="x domain", yref="y domain", x=0.02,
                       y=0.98, showarrow=False, xanchor="left", font={"size": 9},
                       row=row, col=col)  # fmt: skip


def robustness_curves(rows: list[dict]) -> go.Figure:
    """MAE ratio to nominal against each shift's strength, one panel per shift, one colour and
    marker per model (a legend click hides a model in every panel)."""
    models = list(dict.fromkeys(r["model"] for r in rows))
    curves = ratio_curves(rows)
    kinds = list(curves)
    cols = 4
    n_rows = (len(kinds) + cols - 1) // cols
    fig = make_subplots(n_rows, cols, subplot_titles=kinds, vertical_spacing=0.1)
    for m, model in enumerate(models):
        for k, kind in enumerate(kinds):
            if model not in curves[kind]:
                continue
            xs, ratios = curves[kind][model]
            fig.add_trace(
                go.Scatter(
                    x=xs, y=ratios, name=model,
                    legendgroup=model, showlegend=k == 0, mode="lines+markers",
                    line={"color": style(m)["color"]},
                    marker={"symbol": style(m)["symbol"], "size": 8},
                    hovertemplate=f"{kind} %{{x}}: %{{y:.2f}}x nominal<extra>{model}</extra>",
                ),
                k // cols + 1, k % cols + 1,
            )  # fmt: skip
    for k, kind in enumerate(kinds):
        row, col = k // cols + 1, k % cols + 1
        fig.update_xaxes(title={"text": strength_unit(kind), "font": {"size": 10}},
                         row=row, col=col)  # fmt: skip
        _nets_scale(fig, curves[kind], row, col)
    fig.add_hline(y=1.0, line={"color": "grey", "width": 1, "dash": "dot"})
    fig.update_layout(
        **LAYOUT, height=300 * n_rows + 160, title="MAE on the shifted twin / nominal MAE",
        legend={"orientation": "h", "y": -0.08},
    )  # fmt: skip
    fig.update_annotations(font_size=11)
    return fig
