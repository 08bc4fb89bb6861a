"""Full-field export (VTU, XDMF) and an off-screen picture of the machine.

Files carry coordinates in mm, temperature in °C and displacement in µm, so a
person opening them in ParaView reads the units of the machine drawing.
"""

from __future__ import annotations

import contextlib
import logging
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from hybridcomp.fem import assembly
from hybridcomp.fem.model import ThermoElasticModel, _material_arrays

if TYPE_CHECKING:
    import meshio

log = logging.getLogger(__name__)


def displacement_fields(model: ThermoElasticModel, states_K: list[np.ndarray]) -> list[np.ndarray]:
    """Displacement (n × 3) [m] of temperature-rise states [K] with the machine's supports."""
    from hybridcomp.fem.model import _support_dofs, solve_supported

    mm = model.mesh
    basis = assembly.cell_basis(mm.mesh)
    mats = _material_arrays(model.machine, mm)
    Ku, Fth = assembly.elastic_operators(basis, mats["E"], mats["nu"], mats["alpha"])
    sol, _ = solve_supported(Ku, np.column_stack([Fth @ x for x in states_K]), _support_dofs(model.machine, mm), mm.mesh.p)
    out = []
    for j in range(len(states_K)):
        out.append(sol[:, j].reshape(-1, 3))
    return out


def _meshio(model: ThermoElasticModel, point_data: dict) -> meshio.Mesh:
    from skfem.io.meshio import to_meshio

    m = to_meshio(model.mesh.mesh, point_data=point_data, cell_data={"body": [model.mesh.body_of_element.astype(np.int32)]},
                  encode_cell_data=False)
    m.points = m.points * 1e3
    return m


def write_fields(model: ThermoElasticModel, out_dir: str | Path, steps: dict[int, np.ndarray], time_s: np.ndarray,
                 fmt: str = "vtu", with_displacement: bool = True) -> list[Path]:
    """Write the stored steps' temperature (and displacement) fields.

    Parameters
    ----------
    steps : {step index: temperature rise [K]}
    fmt : ``"vtu"`` (one file per step) or ``"xdmf"`` (one time series; needs h5py)
    """
    import meshio

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    keys = sorted(steps)
    disp = displacement_fields(model, [steps[k] for k in keys]) if with_displacement and keys else [None] * len(keys)
    t_ref = model.reference_temperature_degC
    written = []
    if fmt == "vtu":
        for k, u in zip(keys, disp):
            pdata = {"temperature_degC": steps[k] + t_ref}
            if u is not None:
                pdata["displacement_um"] = u * 1e6
            path = out_dir / f"field_{k:05d}.vtu"
            meshio.write(path, _meshio(model, pdata))
            written.append(path)
    elif fmt == "xdmf":
        try:
            import h5py  # noqa: F401
        except ImportError:
            raise RuntimeError("XDMF export needs h5py: pip install 'hybridcomp[xdmf]'") from None
        path = out_dir / "fields.xdmf"
        base = _meshio(model, {})
        # meshio writes the .h5 beside the working directory, not beside the .xdmf: write from out_dir
        with contextlib.chdir(out_dir), meshio.xdmf.TimeSeriesWriter(path.name) as w:
            w.write_points_cells(base.points, base.cells)
            for k, u in zip(keys, disp):
                pdata = {"temperature_degC": steps[k] + t_ref}
                if u is not None:
                    pdata["displacement_um"] = u * 1e6
                w.write_data(float(time_s[k]), point_data=pdata)
        written.append(path)
    else:
        raise ValueError(f"unknown field format {fmt!r}: use 'vtu' or 'xdmf'")
    return written


def _select_offscreen_backend() -> None:
    """Pick VTK's EGL or OSMesa window without an X server; fail clearly where VTK would segfault."""
    import ctypes.util
    import os

    if os.environ.get("DISPLAY") or os.environ.get("VTK_DEFAULT_OPENGL_WINDOW"):
        return
    if ctypes.util.find_library("EGL"):
        os.environ["VTK_DEFAULT_OPENGL_WINDOW"] = "vtkEGLRenderWindow"
    elif ctypes.util.find_library("OSMesa"):
        os.environ["VTK_DEFAULT_OPENGL_WINDOW"] = "vtkOSOpenGLRenderWindow"
    else:
        raise RuntimeError(
            "off-screen rendering needs Mesa's EGL or OSMesa "
            "(Debian: apt-get install libegl1 libgl1-mesa-dri libosmesa6); the PNG was not made"
        )


def render_png(model: ThermoElasticModel, state_K: np.ndarray, path: str | Path, title: str = "",
               warp_scale: float | None = None, size: tuple[int, int] = (1400, 1000)) -> Path:
    """Off-screen PNG: temperature on the deformed machine (deformation exaggerated).

    Needs pyvista (extra ``plot``) and an off-screen OpenGL (Mesa EGL or OSMesa).
    """
    _select_offscreen_backend()
    try:
        import pyvista as pv
    except ImportError:
        raise RuntimeError("rendering needs pyvista: pip install 'hybridcomp[plot]'") from None
    u = displacement_fields(model, [state_K])[0]
    grid = pv.from_meshio(_meshio(model, {"temperature_degC": state_K + model.reference_temperature_degC,
                                          "displacement_um": u * 1e6}))
    extent_mm = float(np.ptp(model.mesh.mesh.p, axis=1).max() * 1e3)
    umax_mm = float(np.abs(u).max() * 1e3)
    scale = warp_scale if warp_scale is not None else (0.05 * extent_mm / umax_mm if umax_mm > 0 else 1.0)
    grid.point_data["displacement_mm"] = u * 1e3
    warped = grid.warp_by_vector("displacement_mm", factor=scale)
    pv.OFF_SCREEN = True
    pl = pv.Plotter(off_screen=True, window_size=list(size))
    pl.set_background("white")
    pl.add_mesh(grid.extract_feature_edges(), color="grey", opacity=0.25)
    pl.add_mesh(warped, scalars="temperature_degC", cmap="inferno", show_edges=False,
                scalar_bar_args={"title": "temperature [°C]\n", "color": "black", "vertical": True,
                                 "position_x": 0.86, "position_y": 0.2, "width": 0.05, "height": 0.6,
                                 "n_labels": 5, "fmt": "%.1f", "title_font_size": 16, "label_font_size": 14})
    pl.add_text(f"{title}\ndeformation x{scale:.0f}, largest displacement {umax_mm * 1e3:.1f} µm", font_size=11, color="black")
    pl.camera_position = "iso"
    pl.camera.azimuth = 200
    pl.camera.elevation = 10
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    pl.screenshot(str(path))
    pl.close()
    return path
