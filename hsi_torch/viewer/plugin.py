"""The napari plugin: a reader for our cube files and a dock widget of spectra at clicked points.

Registered through the npe2 manifest ``hsi_torch/viewer/napari.yaml`` (entry point
``napari.manifest``), so ``pip install 'hsi-torch[viewer]'`` makes napari open our files and list
the widget under *Plugins → hsi-torch*. ``hsi-torch view FILE`` opens files with both
(:func:`view`).

* :func:`napari_get_reader` — the reader contribution: any path :func:`~hsi_torch.viewer.data.
  is_cube_path` accepts gives the band stack (nm axis) and the sRGB composite
  (:func:`~hsi_torch.viewer.data.read_layers`).
* :class:`SpectrumWidget` — the dock widget: a click on the image adds the spectrum under the
  click to the plot (several at once, each in its own colour, with a ±σ band when the cube has a
  standard deviation; a click outside the valid mask adds nothing and says so); the spectrum
  under the cursor is drawn as a dashed line while the mouse moves; a band slider labelled in nm
  moves the viewer to that band (and napari's own band slider is labelled with the band's
  wavelength, for every file format); *Clear* empties the plot. Pixels are ``(row, col)``, napari's
  order. On a run store's frame axis the plotted spectra follow the displayed frame: moving to
  another frame replots every point from that frame.

This module imports napari, Qt and matplotlib's Qt backend: only napari (through the manifest) and
the ``view`` command import it.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.backends.backend_qtagg import FigureCanvasQTAgg
from matplotlib.colors import to_hex
from matplotlib.figure import Figure
from qtpy.QtCore import Qt
from qtpy.QtWidgets import QHBoxLayout, QLabel, QPushButton, QSlider, QVBoxLayout, QWidget

from hsi_torch.io.atomic import atomic_write
from hsi_torch.viewer.data import Spectrum, is_cube_path, read_layers, spectrum_at

__all__ = ["napari_get_reader", "SpectrumWidget", "view", "SCREENSHOT_SOFTWARE"]

#: The PNG ``Software`` text of a screenshot written by ``hsi-torch view --screenshot``.
SCREENSHOT_SOFTWARE = "hsi-torch view"


def napari_get_reader(path: str | Sequence[str]) -> Callable[[Any], list] | None:
    """npe2 reader contribution: a reader function for our cube files, else None."""
    paths = [path] if isinstance(path, (str, os.PathLike)) else list(path)
    if not paths or not all(is_cube_path(p) for p in paths):
        return None
    return _read


def _read(path: str | Sequence[str]) -> list:
    paths = [path] if isinstance(path, (str, os.PathLike)) else list(path)
    out: list = []
    for p in paths:
        out.extend(read_layers(p))
    return out


class SpectrumWidget(QWidget):
    """Spectra at clicked points of the band-stack layers (module docstring).

    Args:
        napari_viewer: the viewer (napari passes it by this name).
        max_points: the oldest clicked point is dropped beyond this many.
    """

    def __init__(self, napari_viewer: Any, max_points: int = 8) -> None:
        super().__init__()
        self.viewer = napari_viewer
        self.max_points = int(max_points)
        self.points: list[tuple[str, Spectrum]] = []  # (layer name, spectrum)
        self.hover: Spectrum | None = None
        self.figure = Figure(figsize=(4, 3), tight_layout=True)
        self.canvas = FigureCanvasQTAgg(self.figure)
        self.ax = self.figure.add_subplot(111)
        self.status = QLabel("click on the image to plot a spectrum")
        self.slider = QSlider(Qt.Horizontal)
        self.band_label = QLabel("")
        clear = QPushButton("Clear")
        clear.clicked.connect(self.clear)
        row = QHBoxLayout()
        row.addWidget(QLabel("band"))
        row.addWidget(self.slider, 1)
        row.addWidget(self.band_label)
        lay = QVBoxLayout(self)
        lay.addWidget(self.canvas, 1)
        lay.addLayout(row)
        lay.addWidget(self.status)
        lay.addWidget(clear)
        self.slider.valueChanged.connect(self._slider_moved)
        self.viewer.mouse_drag_callbacks.append(self._on_click)
        self.viewer.mouse_move_callbacks.append(self._on_move)
        self.viewer.layers.events.inserted.connect(lambda _e: self._sync_slider())
        self.viewer.dims.events.current_step.connect(lambda _e: self._dims_changed())
        self._sync_slider()
        self.redraw()

    # -- the band slider -----------------------------------------------------------------------
    def _layer(self) -> Any | None:
        layers = [ly for ly in self.viewer.layers if ly.metadata.get("hsi_torch")]
        sel = self.viewer.layers.selection.active
        if sel is not None and sel in layers:
            return sel
        return layers[-1] if layers else None

    def wavelengths(self) -> np.ndarray | None:
        """The band centres (nm) of the current band-stack layer."""
        ly = self._layer()
        return None if ly is None else np.asarray(ly.metadata["wavelengths_nm"])

    def _band_dim(self, layer: Any) -> int:
        # the band axis is the layer's third-last; layers align on their last axes
        return self.viewer.dims.ndim - 3

    def _sync_slider(self) -> None:
        wl = self.wavelengths()
        if wl is None:
            self.slider.setEnabled(False)
            self.band_label.setText("")
            return
        self.slider.setEnabled(True)
        self.slider.blockSignals(True)
        self.slider.setRange(0, len(wl) - 1)
        self.slider.setValue(self.current_band())
        self.slider.blockSignals(False)
        self.band_label.setText(f"{wl[self.slider.value()]:.0f} nm")
        self._label_band_axis()

    def _label_band_axis(self) -> None:
        """Name napari's band slider by the shown band's wavelength (``"550 nm"``): its own
        label is the band index, and the axis is in nm only for a uniform grid."""
        ly, wl = self._layer(), self.wavelengths()
        if ly is None or wl is None:
            return
        dim = self._band_dim(ly)
        labels = list(self.viewer.dims.axis_labels)
        text = f"{wl[self.current_band()]:.0f} nm"
        if 0 <= dim < len(labels) and labels[dim] != text:
            labels[dim] = text
            self.viewer.dims.axis_labels = labels

    def current_frame(self) -> int | None:
        """The frame the viewer shows of a run store's band stack (None for a single cube)."""
        ly = self._layer()
        if ly is None or ly.data.ndim != 4:
            return None
        d = ly.world_to_data(list(self.viewer.dims.point))
        return int(np.clip(round(float(d[0])), 0, ly.data.shape[0] - 1))

    def current_band(self) -> int:
        """The band the viewer shows (index into :meth:`wavelengths`)."""
        ly = self._layer()
        if ly is None:
            return 0
        world = list(self.viewer.dims.point)
        data = ly.world_to_data(world)
        m = len(ly.metadata["wavelengths_nm"])
        return int(np.clip(round(float(data[-3])), 0, m - 1))

    def set_band(self, index: int) -> None:
        """Show band ``index`` (the slider does this)."""
        ly = self._layer()
        if ly is None:
            return
        world = np.asarray(self.viewer.dims.point, np.float64)
        data = np.asarray(ly.world_to_data(world), np.float64)
        data[-3] = float(index)
        target = np.asarray(ly.data_to_world(data), np.float64)
        self.viewer.dims.set_point(self._band_dim(ly), float(target[-3]))

    def _slider_moved(self, value: int) -> None:
        self.set_band(int(value))
        wl = self.wavelengths()
        if wl is not None:
            self.band_label.setText(f"{wl[int(value)]:.0f} nm")

    def _dims_changed(self) -> None:
        wl = self.wavelengths()
        if wl is None:
            return
        b = self.current_band()
        if self.slider.value() != b:
            self.slider.blockSignals(True)
            self.slider.setValue(b)
            self.slider.blockSignals(False)
        self.band_label.setText(f"{wl[b]:.0f} nm")
        self._label_band_axis()
        self._follow_frame()

    def _follow_frame(self) -> None:
        """Replot every point of a run store from the displayed frame (a pixel not valid in
        that frame is drawn as a gap)."""
        frame = self.current_frame()
        if frame is None or all(sp.frame in (None, frame) for _, sp in self.points):
            return
        moved: list[tuple[str, Spectrum]] = []
        for name, sp in self.points:
            ly = self.viewer.layers[name] if name in self.viewer.layers else None
            if ly is None or ly.data.ndim != 4 or sp.frame == frame:
                moved.append((name, sp))
                continue
            new = spectrum_at(ly.data, ly.metadata, sp.row, sp.col, frame)
            if new is None:  # not valid in this frame: the point stays, without a curve
                new = Spectrum(sp.row, sp.col, sp.wavelengths_nm,
                               np.full_like(sp.values, np.nan), None, frame)  # fmt: skip
            moved.append((name, new))
        self.points = moved
        self.redraw()

    # -- points ---------------------------------------------------------------------------------
    def spectrum_at_world(self, position: Sequence[float]) -> tuple[str, Spectrum] | None:
        """The spectrum of the current band-stack layer at a world position (None outside the
        image or the valid mask)."""
        ly = self._layer()
        if ly is None:
            return None
        d = ly.world_to_data(list(position))
        frame = int(round(float(d[0]))) if ly.data.ndim == 4 else None
        sp = spectrum_at(ly.data, ly.metadata, d[-2], d[-1], frame)
        return None if sp is None else (ly.name, sp)

    def add_point(self, position: Sequence[float]) -> Spectrum | None:
        """Add the spectrum at a world position to the plot; None (and a message) outside the
        valid mask."""
        hit = self.spectrum_at_world(position)
        if hit is None:
            self.status.setText("no spectrum there: outside the image or its valid region")
            return None
        self.points.append(hit)
        self.points = self.points[-self.max_points:]
        self._mark_points()
        sp = hit[1]
        self.status.setText(f"{len(self.points)} point(s); last: row {sp.row}, col {sp.col}")
        self.redraw()
        return sp

    def _mark_points(self) -> None:
        """Show the clicked pixels on the image, in their curves' colours (a Points layer)."""
        ly = self._layer()
        if ly is None:
            return
        coords = []
        for _, sp in self.points:
            d = np.asarray(ly.world_to_data(list(self.viewer.dims.point)), np.float64)
            d[-2], d[-1] = sp.row, sp.col
            coords.append(np.asarray(ly.data_to_world(d))[-2:])
        data = np.asarray(coords, np.float64).reshape(-1, 2)
        colours = [to_hex(f"C{i % 10}") for i in range(len(data))]
        name = "spectrum points"
        if name in self.viewer.layers:
            pts = self.viewer.layers[name]
            pts.data = data
            pts.face_color = colours if len(data) else "white"
        else:
            self.viewer.add_points(data, name=name, size=3, face_color=colours,
                                   border_color="white", border_width=0.15)  # fmt: skip
            self.viewer.layers.selection.active = ly  # clicks keep going to the cube

    def clear(self) -> None:
        """Remove every point."""
        self.points = []
        self._mark_points()
        self.status.setText("click on the image to plot a spectrum")
        self.redraw()

    def _on_click(self, _viewer: Any, event: Any) -> None:
        if event.type == "mouse_press" and getattr(event, "button", 1) == 1:
            self.add_point(event.position)

    def _on_move(self, _viewer: Any, event: Any) -> None:
        hit = self.spectrum_at_world(event.position)
        self.hover = None if hit is None else hit[1]
        self.redraw()

    # -- drawing ---------------------------------------------------------------------------------
    def redraw(self) -> None:
        """Redraw the plot: every clicked point (±σ shaded when known), the hovered one dashed."""
        ax = self.ax
        ax.clear()
        colours = [f"C{i}" for i in range(10)]
        for i, (_name, sp) in enumerate(self.points):
            col = colours[i % 10]
            where = f" frame {sp.frame}" if sp.frame is not None else ""
            ax.plot(sp.wavelengths_nm, sp.values, color=col, lw=1.5,
                    label=f"({sp.row}, {sp.col}){where}")  # fmt: skip
            if sp.std is not None:
                ax.fill_between(sp.wavelengths_nm, sp.values - sp.std, sp.values + sp.std,
                                color=col, alpha=0.25, lw=0)  # fmt: skip
        if self.hover is not None:
            ax.plot(self.hover.wavelengths_nm, self.hover.values, "k--", lw=1, label="cursor")
        ax.set_xlabel("wavelength (nm)")
        ax.set_ylabel("reflectance")
        if self.points or self.hover is not None:
            ax.legend(fontsize=7, loc="best")
        ax.grid(alpha=0.3)
        self.canvas.draw_idle()


def view(
    paths: Sequence[str | os.PathLike],
    *,
    screenshot: str | os.PathLike | None = None,
    points: Sequence[tuple[float, float]] = (),
    band_nm: float | None = None,
) -> Any:
    """Open cube files in napari with the spectrum widget docked (``hsi-torch view``).

    Args:
        paths: cube files or run stores.
        screenshot: write a PNG of the whole window (viewer + widget) and close instead of
            running the event loop (for scripts and tests).
        points: ``(row, col)`` pixels to plot at once, as if clicked.
        band_nm: show the band nearest this wavelength.

    Returns:
        The viewer (closed when ``screenshot`` is given).
    """
    import napari  # lazy: the plugin's optional dependency, loaded only by this command

    for p in paths:
        if not Path(p).exists():
            raise FileNotFoundError(f"cube file not found: {p}")
        if not is_cube_path(p):
            raise ValueError(f"{p}: not a cube file (expected one of .tif .hdr .npz .nc .zarr)")
    viewer = napari.Viewer(show=screenshot is None)
    for p in paths:
        for data, kw, kind in read_layers(p):
            getattr(viewer, f"add_{kind}")(data, **kw)
    band = [ly for ly in viewer.layers if ly.metadata.get("hsi_torch")]
    if band:  # the band stack on top, selected: the sRGB composite is one click away
        viewer.layers.move(viewer.layers.index(band[-1]), len(viewer.layers))
        viewer.layers.selection.active = band[-1]
    widget = SpectrumWidget(viewer)
    viewer.window.add_dock_widget(widget, name="spectra (hsi-torch)", area="right")
    if band_nm is not None and widget.wavelengths() is not None:
        widget.slider.setValue(int(np.argmin(np.abs(widget.wavelengths() - float(band_nm)))))
    for r, c in points:
        ly = widget._layer()
        d = np.asarray(ly.world_to_data(list(viewer.dims.point)), np.float64)  # shown frame
        d[-2], d[-1] = r, c
        widget.add_point(ly.data_to_world(d))
    if screenshot is not None:
        from qtpy.QtWidgets import QApplication  # lazy: with napari

        viewer.window.resize(1400, 760)
        QApplication.processEvents()  # the dock widget's space is taken before fitting the view
        viewer.reset_view()
        widget.canvas.draw()
        img = viewer.screenshot(canvas_only=False, flash=False)
        import matplotlib.image as mpimg  # lazy: only for the screenshot

        Path(screenshot).parent.mkdir(parents=True, exist_ok=True)
        with atomic_write(screenshot, "wb") as f:  # an earlier PNG kept until this one is whole
            # the tag tells a later --screenshot that this PNG is ours to replace
            mpimg.imsave(f, img, format="png", metadata={"Software": SCREENSHOT_SOFTWARE})
        viewer.close()
        return viewer
    napari.run()
    return viewer
