"""Geometry of a triangle mesh that every mesh source needs: vertex normals, UV seams."""

from __future__ import annotations

import numpy as np


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted vertex normals, (..., V, 3); isolated vertices get +Y."""
    batched = vertices if vertices.ndim == 3 else vertices[None]
    v0, v1, v2 = (batched[:, faces[:, k], :].astype(np.float64) for k in range(3))
    face_n = np.cross(v1 - v0, v2 - v0)  # length = 2 * area: area weighting for free
    normals = np.zeros(batched.shape, dtype=np.float64)
    for k in range(3):
        np.add.at(normals, (slice(None), faces[:, k]), face_n)
    normals = normals if vertices.ndim == 3 else normals[0]
    length = np.linalg.norm(normals, axis=-1, keepdims=True)
    fallback = np.zeros_like(normals)
    fallback[..., 1] = 1.0
    return np.where(length > 1e-12, normals / np.maximum(length, 1e-30), fallback).astype(np.float32)


def split_uv_seams(faces: np.ndarray, face_uv_indices: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Turn (position index, UV index) corners into one vertex per unique pair.

    Returns new faces (F, 3), the position index of each new vertex, and the UV index of each new vertex.
    """
    pairs = np.stack([faces.ravel(), face_uv_indices.ravel()], axis=1)
    unique, inverse = np.unique(pairs, axis=0, return_inverse=True)
    return inverse.reshape(faces.shape).astype(np.int32), unique[:, 0], unique[:, 1]
