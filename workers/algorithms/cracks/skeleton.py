"""Thin a crack mask to a strictly 8-thin skeleton: Zhang-Suen thinning (Zhang & Suen, CACM 1984), then the
remaining simple non-end points deleted one at a time (Rosenfeld's simple-point test)."""

from __future__ import annotations

from functools import lru_cache

import cv2
import numpy as np
from scipy import ndimage as ndi

# Neighbour k of a pixel, in the ring order N, NE, E, SE, S, SW, W, NW (Zhang & Suen's P2..P9): (drow, dcol).
EIGHT_CONNECTED = np.ones((3, 3), dtype=bool)  # ndimage structure: 8-connected neighbours
RING = ((-1, 0), (-1, 1), (0, 1), (1, 1), (1, 0), (1, -1), (0, -1), (-1, -1))


def _neighbour_codes(image: np.ndarray) -> np.ndarray:
    """(H, W) uint8: bit k set where ring neighbour k (see ``RING``) of a pixel is set in the bool ``image``."""
    padded = np.pad(image, 1)
    h, w = image.shape
    code = np.zeros((h, w), np.uint8)
    for bit, (dr, dc) in enumerate(RING):
        code |= padded[1 + dr : 1 + dr + h, 1 + dc : 1 + dc + w].astype(np.uint8) << bit
    return code


def _ring_bits(code: int) -> list[int]:
    return [(code >> k) & 1 for k in range(8)]


@lru_cache(maxsize=1)
def _zhang_suen_tables() -> tuple[np.ndarray, np.ndarray]:
    """Deletion tables of the two Zhang-Suen sub-iterations, indexed by neighbour code: (256,) bool each.

    With Lu & Wang's correction: Zhang-Suen's own test (2 <= B) erases lines two pixels thick on diagonals.
    """
    tables = np.zeros((2, 256), dtype=bool)
    for code in range(256):
        p = _ring_bits(code)  # p[0..7] = P2..P9
        transitions = sum(p[k] == 0 and p[(k + 1) % 8] == 1 for k in range(8))
        if 3 <= sum(p) <= 6 and transitions == 1:  # 3, not 2: Lu & Wang (CACM 1986) keep 2-px diagonals
            tables[0, code] = p[0] * p[2] * p[4] == 0 and p[2] * p[4] * p[6] == 0
            tables[1, code] = p[0] * p[2] * p[6] == 0 and p[0] * p[4] * p[6] == 0
    return tables[0], tables[1]


@lru_cache(maxsize=1)
def _removable_table() -> np.ndarray:
    """(256,) bool: deleting the centre changes neither topology nor the ends of the skeleton.

    The centre must be a simple point (Rosenfeld 1970, 8-connected foreground: the foreground neighbours
    form one 8-connected set, the background neighbours 4-adjacent to the centre one 4-connected set of the
    ring) with three or more neighbours, or exactly two that are perpendicular 4-neighbours (the corner of a
    4-connected staircase). A pixel with a 4- and an adjacent diagonal neighbour is the tip of a line two
    pixels thick: deleting it would shorten the line, one pixel per deletion.
    """
    table = np.zeros(256, dtype=bool)
    four = ndi.generate_binary_structure(2, 1)
    for code in range(1, 256):
        patch = np.zeros((3, 3), dtype=bool)
        for bit, (dr, dc) in enumerate(RING):
            patch[1 + dr, 1 + dc] = (code >> bit) & 1
        if patch.sum() < 2 or (patch.sum() == 2 and code & 0b10101010):  # odd bits: diagonal neighbours
            continue
        fg_components = ndi.label(patch, structure=EIGHT_CONNECTED)[1]
        background = ~patch
        background[1, 1] = False
        labels = ndi.label(background, structure=four)[0]
        touching = {labels[1 + dr, 1 + dc] for dr, dc in RING[::2]} - {0}
        table[code] = fg_components == 1 and len(touching) == 1
    return table


def thin(mask: np.ndarray) -> np.ndarray:
    """One-pixel-wide 8-connected skeleton of a crack mask.

    Zhang & Suen (CACM 27(3), 1984) parallel thinning with Lu & Wang's correction (CACM 29(3), 1986),
    then the simple points it leaves on staircases
    are deleted one at a time, so every skeleton pixel with three or more neighbours is a real junction.

    Parameters
    ----------
    mask : (H, W) bool.

    Returns
    -------
    (H, W) bool skeleton, same connected components as ``mask``.
    """
    image = mask.astype(bool).copy()
    tables = _zhang_suen_tables()
    changed = True
    while changed:
        changed = False
        for table in tables:
            delete = image & table[_neighbour_codes(image)]
            if delete.any():
                image[delete] = False
                changed = True
    return _delete_redundant(image)


def _delete_redundant(skeleton: np.ndarray) -> np.ndarray:
    """Delete, one at a time (so two of them never go together), simple non-end points of a thin skeleton."""
    removable = _removable_table()
    padded = np.pad(skeleton, 1)
    rows, cols = np.nonzero(skeleton & removable[_neighbour_codes(skeleton)])
    for r, c in zip(rows + 1, cols + 1, strict=True):
        code = sum(int(padded[r + dr, c + dc]) << bit for bit, (dr, dc) in enumerate(RING))
        if removable[code]:
            padded[r, c] = False
    return padded[1:-1, 1:-1]


def neighbour_count(skeleton: np.ndarray) -> np.ndarray:
    """(H, W) int32: number of 8-neighbours of each pixel that are set."""
    kernel = np.ones((3, 3), np.float32)
    kernel[1, 1] = 0
    return np.rint(cv2.filter2D(skeleton.astype(np.float32), -1, kernel, borderType=cv2.BORDER_CONSTANT)).astype(
        np.int32
    )
