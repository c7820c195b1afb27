"""Build configuration that ``pyproject.toml`` cannot express: the shipped configuration files.

They live once, in ``configs/`` beside the package (where a checkout's reader looks for them),
and are installed as the data-only package ``hsi_torch.configs`` (``configs/*.yaml`` →
``hsi_torch/configs/*.yaml`` in a wheel; an sdist carries ``configs/``), where
:mod:`hsi_torch.resources` finds them with :mod:`importlib.resources`. Editable installs and
source checkouts run with ``PYTHONPATH`` read them from ``configs/`` directly. Everything else
(metadata, dependencies, entry point) is in ``pyproject.toml``.
"""

from setuptools import find_packages, setup

setup(
    packages=[*find_packages(include=["hsi_torch", "hsi_torch.*"]), "hsi_torch.configs"],
    package_dir={"hsi_torch.configs": "configs"},
    package_data={"hsi_torch": ["data/*", "io/*.schema.json", "viewer/napari.yaml"],
                  "hsi_torch.configs": ["*.yaml"]},
)
