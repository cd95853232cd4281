"""The one in-memory scene every loader produces (numpy, torch-free)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class Scene:
    """A multi-view image set with pinhole cameras, normalised into the unit sphere.

    Conventions:
        * Cameras are OpenCV pinhole (x right, y down, z forward), already undistorted.
        * ``c2w`` maps camera coordinates to *normalised* coordinates, where the object
          of interest lies inside the unit sphere.
        * ``world_from_norm`` maps normalised coordinates back to the input's world:
          ``x_world = world_from_norm @ [x_norm, 1]`` (a similarity: uniform scale,
          rotation, translation).

    Attributes:
        images: ``[N, H, W, 3]`` float32, **linear** RGB in [0, 1] (sRGB decoded).
        masks: ``[N, H, W]`` bool foreground masks, or None when the data has none.
        intrinsics: ``[N, 3, 3]`` float32 pixel-unit K with pixel centres at +0.5: the centre of
            pixel (column i, row j) is at (u, v) = (i + 0.5, j + 0.5), so a centred camera has
            cx = W / 2 (the NeRF/Blender convention; DTU loaders add 0.5 to OpenCV's cx, cy).
        c2w: ``[N, 4, 4]`` float32 camera-to-normalised-world.
        world_from_norm: ``[4, 4]`` float64 similarity back to input world coordinates.
        names: per-view source image path, relative to ``root``.
        root: dataset folder the scene was loaded from.
        source_format: ``"dtu" | "blender" | "ingp" | "nerfstudio" | "colmap" | "synthetic"``.
        split: which split the views belong to (``"train"``, ``"test"``, ``"all"``).
        points: ``[P, 3]`` float32 sparse points of the capture's own structure from motion
            (COLMAP ``points3D``, nerfstudio ``ply_file_path``) in the normalised frame, or None:
            without masks the object region is looked for among them, else among points
            triangulated from the images (``nepf_core/train/rules/masks.py``).
    """

    images: np.ndarray
    masks: np.ndarray | None
    intrinsics: np.ndarray
    c2w: np.ndarray
    world_from_norm: np.ndarray
    names: list[str]
    root: str = ""
    source_format: str = "unknown"
    split: str = "all"
    extras: dict = field(default_factory=dict)
    points: np.ndarray | None = None

    @property
    def n_views(self) -> int:
        return int(self.images.shape[0])

    @property
    def height(self) -> int:
        return int(self.images.shape[1])

    @property
    def width(self) -> int:
        return int(self.images.shape[2])

    @property
    def has_masks(self) -> bool:
        return self.masks is not None

    def world_scale(self) -> float:
        """Uniform scale s of ``world_from_norm`` (world units per normalised unit)."""
        return float(np.cbrt(abs(np.linalg.det(self.world_from_norm[:3, :3]))))

    def subset(self, idx) -> "Scene":
        """A new Scene with the views ``idx`` (list or array of ints)."""
        idx = np.asarray(idx, dtype=np.int64)
        return Scene(
            images=self.images[idx], masks=None if self.masks is None else self.masks[idx],
            intrinsics=self.intrinsics[idx], c2w=self.c2w[idx],
            world_from_norm=self.world_from_norm, names=[self.names[i] for i in idx],
            root=self.root, source_format=self.source_format, split=self.split,
            extras=dict(self.extras), points=self.points,
        )
