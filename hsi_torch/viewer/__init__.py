"""Looking at cubes: a napari plugin (reader + spectrum dock widget) and ``hsi-torch view``.

Needs the ``[viewer]`` extra (``pip install 'hsi-torch[viewer]'``: napari with a Qt binding).
This package imports no napari or Qt itself: :mod:`hsi_torch.viewer.data` (what the layers hold,
spectra at points) needs only the core dependencies, :mod:`hsi_torch.viewer.plugin` (the napari
side) is imported by napari through the npe2 manifest ``napari.yaml`` or by ``hsi-torch view``.
"""
