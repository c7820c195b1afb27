"""Re-render only the captures a calibration → capture effect changes, beside an existing set.

Drift, a filter temperature change and another scene illuminant (the ``after_calibration``
effects of :class:`~hsi_torch.simulate.mismatch.Mismatch`) act on the scene captures only: the
scan, white, grid and dark frames, the ground truth and therefore the calibration are those of
the ideal device. :func:`rerender_after_calibration` renders the scene captures (optionally also
the white references: a white reference shot under the scene's light) with the config's
mismatch, writes them into a new folder and hard-links (or copies) every other file of a base
capture set rendered from the same config without the effect (device effects of the base set
must be the config's too). At full size this skips the scan's 25 frames, the grids and the
truth: one render pass instead of a whole set.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from hsi_torch.io import write_capture
from hsi_torch.io.atomic import atomic_write_text, link_or_copy
from hsi_torch.io.capture_set import TRUTH_JSON, read_truth_meta
from hsi_torch.simulate.capture_sets import (
    _capture_metadata,
    build_renderer,
    plan_captures,
)
from hsi_torch.simulate.config import SimulateConfig

__all__ = ["rerender_after_calibration"]


#: the mismatch keys of effects that act after calibration (re-rendered by
#: :func:`rerender_after_calibration`; ``white_mismatch`` records those a re-shot white got)
AFTER_CALIBRATION_KEYS = ("drift_shift_px", "drift_rotation_deg", "brf_delta_t_k",
                          "scene_illuminant", "brf_retardance_temp_coeff_per_k")


def white_mismatch_of(cfg_mismatch: Any) -> dict[str, Any]:
    """The ``white_mismatch`` record white references rendered with ``cfg_mismatch`` (a
    :class:`~hsi_torch.simulate.config.SimulateConfig`'s ``mismatch``) get: its active
    after-calibration keys, JSON-normalised."""
    return _jsonable({k: v for k, v in cfg_mismatch.active().items()
                      if k in AFTER_CALIBRATION_KEYS})


def _jsonable(d: dict[str, Any]) -> dict[str, Any]:
    return json.loads(json.dumps({k: list(v) if isinstance(v, tuple) else v for k, v in d.items()}))


def _base_mismatch(base: Path) -> dict[str, Any]:
    """The base set's recorded mismatch keys (``{}``: an ideal set, or no record)."""
    return dict(read_truth_meta(base).get("mismatch") or {})


def rerender_after_calibration(
    cfg: SimulateConfig,
    base_dir: str | Path,
    out_dir: str | Path,
    *,
    whites: bool = False,
    scenes: bool = True,
    device: str | None = None,
    log=print,
) -> list[str]:
    """Write ``out_dir``: ``base_dir``'s capture set with its scene captures (and, with
    ``whites``, its white references) rendered anew by ``cfg`` after calibration.

    ``cfg`` must be the config ``base_dir`` was rendered from plus ``after_calibration``
    mismatch keys (drift, ``brf_delta_t_k``, ``scene_illuminant``): the planned files and noise
    seeds are the base's, so with no such key the rendered files equal the base's bit for bit.
    Device effects (distortion, stray light, …) change the calibration frames too: they must be
    the base set's own (its ``truth.json`` ``mismatch`` record), else they are refused. Every
    other file of ``base_dir`` is hard-linked (copied across file systems; a link is replaced,
    never written through); ``ground_truth/truth.json`` gets the config's ``mismatch`` record
    (with ``scenes=False`` the base's stays), and with ``whites`` its after-calibration keys as
    ``white_mismatch``.

    Args:
        cfg: simulate config (``cfg.mismatch`` holds the effects).
        base_dir: the base capture set (read only).
        out_dir: the new set's folder (created; its re-rendered files are replaced).
        whites: also render the ``white`` captures with the after-calibration effects (under
            the scene's light).
        scenes: render the scene captures (``False``: keep the base's; needs ``whites``).

    Returns:
        The re-rendered files, relative to ``out_dir``.

    Raises:
        ValueError: a device effect the base set lacks is on (or one it has is off), nothing
            is to be rendered, or the base set lacks a planned file.
    """
    base, out = Path(base_dir), Path(out_dir)
    mm = cfg.mismatch
    if not (scenes or whites):
        raise ValueError("rerender_after_calibration: neither scenes nor whites to render")
    device_keys = _jsonable({k: v for k, v in mm.active().items()
                             if k not in AFTER_CALIBRATION_KEYS})
    base_keys = _jsonable({k: v for k, v in _base_mismatch(base).items()
                           if k not in AFTER_CALIBRATION_KEYS})
    if device_keys != base_keys:
        raise ValueError(f"rerender_after_calibration: mismatch keys {sorted(device_keys)} "
                         f"differ from the base set's device keys {sorted(base_keys)}: they "
                         "change the calibration frames too; simulate the whole set instead")
    renderer = build_renderer(cfg, device)
    specs, planned, _ = plan_captures(cfg, renderer, lambda *a: None)
    types = ({"scene"} if scenes else set()) | ({"white"} if whites else set())
    sel = [pc for pc in planned if pc.type in types]
    missing = [pc.file for pc in planned if not (base / pc.file).is_file()]
    if missing:
        raise ValueError(f"{base}: the config plans files the base set lacks: {missing[:5]} "
                         "(was it rendered from another config?)")
    redo = {pc.file for pc in sel}
    out.mkdir(parents=True, exist_ok=True)
    for p in sorted(base.rglob("*")):
        rel = p.relative_to(base).as_posix()
        if p.is_file() and rel not in redo:
            link_or_copy(p, out / rel)  # a hard link: every writer replaces it
    truth_json = out / TRUTH_JSON
    if truth_json.is_file():
        meta = read_truth_meta(out)
        if scenes:
            meta["mismatch"] = mm.active()
        if whites:  # the after-calibration effects the white references were shot with
            meta["white_mismatch"] = white_mismatch_of(mm)
        meta["rerendered_after_calibration"] = sorted(redo)
        # a link to the base's file: a new one replaces it (never written through)
        atomic_write_text(truth_json, json.dumps(meta, indent=1))
    keys = sorted({pc.render_key for pc in sel})
    imgs = renderer.render_captures([specs[k] for k in keys], None, after_calibration=True)
    irr = dict(zip(keys, imgs, strict=True))
    for pc in sel:
        exposure = renderer.exposure_of(pc.spec)
        dn, sat = renderer.expose(irr[pc.render_key], exposure, pc.seed)
        meta = _capture_metadata(renderer, pc, exposure)
        meta["saturated_pixels"] = int(sat.sum())
        write_capture(out / pc.file, dn, meta)  # atomic: a hard link there is replaced
    log(f"re-rendered {len(sel)} capture(s) after calibration into {out}")
    return sorted(redo)
