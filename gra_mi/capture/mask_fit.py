"""The check that an image goes with its mask file. The mask files are checked against the mesh (reprojection.py), but
not the pixels against the masks: images turned, another camera's or another frame's would import under correct
masks and spoil the fit unsaid. A masked (black-background) image is checked by where its light lies; an image that
keeps its background, by where its edges lie: a subject's outline is an edge in its photograph, so the image's
edges line up with its own mask's outline better than with any other mask's."""

from __future__ import annotations

import numpy as np

from gra_mi.capture.placement import CameraPlan
from gra_mi.capture.source import Source
from gra_mi.capture.source_files import orientation_hint, read_image, read_mask
from gra_mi.core.errors import GraMiInputError

MASKED_BACKGROUND = 0.2  # an image with this share of pixels at exactly 0 was masked (black background)
OUTSIDE_MASK = 0.25  # a masked image with this share of its light outside its mask file does not go with it
NEIGHBOUR_OUTSIDE = 0.04  # ... with this share, it does not where another camera's mask holds it BETTER_LIGHT× better
BETTER_LIGHT = 4.0
SIMILAR_AREA = 1.33  # ... a mask at most this much larger or smaller than its own (a larger one holds any light)
MASK_EDGE = 2  # pixels the mask file is grown by first: an edge pixel the subject partly covers is lit on either side
BETTER_OUTLINE = 1.5  # another mask's outline this much better on an image's edges than its own: not its image
CLEAR_OUTLINE = 1.5  # ... and at least this much above the image's mean edge strength (an outline, not noise)
TURNED = "its mask turned 180° (the image turned?)"


def check_images_fit_masks(source: Source, plans: list[CameraPlan], key: int) -> None:
    """Every camera's image of frame ``key`` against its mask file: a masked image by its light outside the mask
    (:func:`_light_outside`), an image with a background by its edges (:func:`_check_outline`). Cameras whose mask
    comes from their pixels are not checked."""
    mask_files = {}
    for plan in plans:
        own = source.frame_masks[plan.index].get(key) if source.frame_masks else None
        if (own or source.masks[plan.index]) is not None:
            mask_files[plan.camera.name] = own or source.masks[plan.index]
    masks = {name: read_mask(path) for name, path in mask_files.items()}
    outlines = {name: (mask.shape, np.flatnonzero(outline(mask))) for name, mask in masks.items()}  # a few kB each
    for plan in (p for p in plans if p.camera.name in masks):
        path = source.images[plan.index][key]
        rgb, _, alpha = read_image(path)
        mask = masks[plan.camera.name]
        # an image with a background (a scene's set shows in its pixels and its alpha): checked by its outlines
        if source.set_shapes or (alpha is None and (rgb.max(axis=-1) == 0).mean() < MASKED_BACKGROUND):
            if mask.shape == rgb.shape[:2]:
                _check_outline(plan.camera.name, path, edge_strength(rgb), outlines)
            continue
        _check_light(plan.camera.name, path, rgb, alpha, masks, mask_files[plan.camera.name])


def _check_light(name: str, path, rgb: np.ndarray, alpha: np.ndarray | None, masks: dict, mask_file) -> None:
    """A masked image against its own mask (``masks[name]``): refused where much of its light lies outside it, or where
    a fair share does and another camera's mask of about the same size holds it several times better (a neighbouring
    camera's image: on a 40-camera stage its neighbours' put 5–30 % of their light outside a camera's own mask)."""
    outside = _light_outside(rgb, alpha, masks[name])
    if outside > OUTSIDE_MASK:
        raise GraMiInputError(
            path, f"camera {name}: {100 * outside:.0f} % of the subject this image shows lies outside its mask "
            f"{mask_file}: the image does not go with it (turned, or another camera's)" + orientation_hint(path),
        )  # fmt: skip
    if outside <= NEIGHBOUR_OUTSIDE:
        return
    area = max(int(masks[name].sum()), 1)
    fits = {
        other: _light_outside(rgb, alpha, mask)
        for other, mask in masks.items()
        if other != name and mask.shape == rgb.shape[:2] and 1 / SIMILAR_AREA <= mask.sum() / area <= SIMILAR_AREA
    }
    best = min(fits, key=fits.get, default=None)
    if best is not None and fits[best] * BETTER_LIGHT < outside:
        raise GraMiInputError(
            path, f"camera {name}: {100 * outside:.1f} % of this image's light lies outside its mask {mask_file}, "
            f"{100 * fits[best]:.1f} % outside camera {best}'s mask: the image looks like camera {best}'s (two cameras' images "
            "swapped?)",
        )  # fmt: skip


def _light_outside(rgb: np.ndarray, alpha: np.ndarray | None, mask: np.ndarray) -> float:
    """The share of a masked image's light (its alpha, for an image with one) outside its mask, grown by
    :data:`MASK_EDGE` pixels. Light, not lit pixels: an OLAT that grazes the subject lights little more than its
    anti-aliased edge."""
    from scipy.ndimage import binary_dilation

    if mask.shape != rgb.shape[:2]:
        return 1.0
    grown = binary_dilation(mask, iterations=MASK_EDGE)
    light = rgb.sum(axis=-1) if alpha is None else alpha
    return float(light[~grown].sum() / max(light.sum(), 1e-30))


def edge_strength(rgb: np.ndarray) -> np.ndarray:
    """|∇| of the image's luminance as a display shows it (sRGB-encoded at its 99th percentile): contrast as seen,
    not ruled by the brightest light."""
    from scipy.ndimage import sobel

    from gra_mi.core.color import srgb_encode

    luminance = rgb.mean(axis=-1, dtype=np.float32)
    top = float(np.partition(luminance.ravel(), int(0.99 * (luminance.size - 1)))[int(0.99 * (luminance.size - 1))])
    shown = srgb_encode(np.clip(luminance / max(top, 1e-12), 0.0, 1.0)).astype(np.float32)
    return np.hypot(sobel(shown, axis=0), sobel(shown, axis=1))


def outline(mask: np.ndarray) -> np.ndarray:
    """A mask's outline: the pixels one step inside or outside its edge."""
    from scipy.ndimage import binary_dilation, binary_erosion

    return binary_dilation(mask, iterations=1) & ~binary_erosion(mask, iterations=1)


def outline_fit(edges: np.ndarray, line: np.ndarray) -> float:
    """How much stronger an image's edges are along an outline (its flat pixel indices) than over the whole image (1:
    unrelated)."""
    return float(edges.ravel()[line].mean() / max(float(edges.mean()), 1e-12)) if line.size else 0.0


def _check_outline(name: str, path, edges: np.ndarray, outlines: dict[str, tuple]) -> None:
    """An image with a background against its own mask's outline, that outline turned 180° and every other camera's
    of its size: one that fits clearly better (:data:`BETTER_OUTLINE`) than its own says the image is not its camera's."""
    own = outline_fit(edges, outlines[name][1])
    others = {TURNED: edges.size - 1 - outlines[name][1]}  # a flat index i, turned 180°, is size − 1 − i
    others |= {
        f"camera {other}'s mask (the image {other}'s?)": line
        for other, (shape, line) in outlines.items()
        if other != name and shape == edges.shape
    }
    what, best = max(((what, outline_fit(edges, line)) for what, line in others.items()), key=lambda item: item[1])
    if best > BETTER_OUTLINE * own and best > CLEAR_OUTLINE:
        raise GraMiInputError(
            path, f"camera {name}: this image's edges follow {what} (outline {best:.1f}× the image's mean edge) "
            f"better than its own mask's (outline {own:.1f}×): the image does not go with its mask"
            + (orientation_hint(path) if what == TURNED else ""),
        )  # fmt: skip
