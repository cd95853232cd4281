"""Mesh of a fitted SDF in world coordinates, and Chamfer distance to a ground-truth mesh."""

from __future__ import annotations

import numpy as np
import trimesh

from nepf_core.evaluate import chamfer_distance


def world_mesh(query, world_from_norm: np.ndarray, resolution: int = 256, device=None) -> trimesh.Trimesh:
    """Marching cubes at SDF = 0 over [-1, 1]^3 (normalised), mapped to the input's world.

    Raises ``nepf_core.export.mesh.EmptyMeshError`` (a ValueError subclass is not
    guaranteed, so callers catch both) when the SDF has no zero crossing.
    """
    from nepf_core.export.mesh import extract_mesh, mesh_to_world
    m = extract_mesh(query.sdf, resolution, (-1.0, 1.0), device=device)
    v, _ = mesh_to_world(np.asarray(m.vertices), world_from_norm)
    return trimesh.Trimesh(vertices=v, faces=np.asarray(m.faces), process=False)


def chamfer_against_gt(query, world_from_norm: np.ndarray, gt_mesh_path: str, resolution: int = 128,
                       n_samples: int = 100_000, device=None) -> tuple[float, float]:
    """``(chamfer_world, chamfer_unit_sphere)`` of the fitted surface against a GT mesh (world).

    Unit-sphere units divide by the uniform scale of ``world_from_norm``.
    """
    from nepf_core.export.mesh import EmptyMeshError
    try:
        mesh = world_mesh(query, world_from_norm, resolution, device=device)
    except EmptyMeshError as e:
        raise ValueError(str(e)) from e
    gt = trimesh.load(gt_mesh_path, force="mesh", process=False)
    cd = chamfer_distance(mesh, gt, n_samples=n_samples)
    scale = float(np.cbrt(abs(np.linalg.det(np.asarray(world_from_norm)[:3, :3]))))
    return cd, cd / scale
