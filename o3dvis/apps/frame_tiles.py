"""One encoding answering pinhole frames: a frame's crop of it (its image, its range), the query of
that crop, and what the frame's users need of the answer: indices, pixels, depths and images.

:class:`FrameTile` holds an encoding of a map (or of a crop of it, see
:class:`~o3dvis.apps.map_frames.FrameMap`) in the order the field stores its points, along the
Morton curve, in blocks of consecutive points whose bounding boxes cull a frame's view at once.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch

from ..cameras import Views
from ..field import VisibilityField
from ..threads import plan_threads, torch_threads
from .pinhole import PinholeView

__all__ = ["Frame", "FrameTile", "frame_images", "empty_frame"]

_BLOCK = 64  # consecutive points (along the Morton curve) whose bounding box culls them at once
_MAX_BLOCKS = 1 << 15
_SPLIT_ROWS = 1 << 16  # a frame's crop of fewer points runs its torch ops on one thread


@dataclass(frozen=True)
class Frame:
    """What one pinhole frame sees of a map.

    Attributes:
        indices: (M,) int64 indices of the visible points in the map, ascending.
        pixels: (M, 2) float32 their image coordinates ``(u, v)`` = (column, row), the centre
            of pixel (row, col) being ``(col, row)`` (Open3D's convention).
        depths: (M,) float32 their depths along the optical axis, in the map's units.
        depth_image: (H, W) float32 depth of the nearest visible point of each pixel, 0 where
            none; None unless asked for.
        index_image: (H, W) int64 index of that point in the map, -1 where none; None unless
            asked for.
    """

    indices: np.ndarray
    pixels: np.ndarray
    depths: np.ndarray
    depth_image: np.ndarray | None = None
    index_image: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.indices)

    def save(self, file) -> None:
        """Writes the frame's arrays (the images where it has them) to an ``.npz`` file: a binary file
        object or a path (``.npz`` is appended to a path without it, as ``np.savez`` does)."""
        images = {"depth_image": self.depth_image, "index_image": self.index_image}
        np.savez(file, indices=self.indices, pixels=self.pixels, depths=self.depths,
                 **{name: image for name, image in images.items() if image is not None})

    @classmethod
    def load(cls, file) -> "Frame":
        """The frame :meth:`save` wrote to ``file`` (a path or a binary file object)."""
        with np.load(file) as arrays:
            return cls(**{name: arrays[name] for name in arrays.files})


class FrameTile:
    """An encoding of (part of) the map and what cropping a frame out of it needs, in the order the
    field stores its points (along the Morton curve): the field itself, its points in that order;
    each point's index in the map and its world coordinates (float64, on the CPU); and the bounding
    boxes of blocks of consecutive points.

    With a scene model, the cameras inside the points' bounding box and those outside it are
    answered by different networks. Given ``encode`` (``encode(inside)``: the encoding that answers
    the cameras on that side), each side is encoded when a camera on it first asks, so that the
    frames of a driving log, all inside, never run the other network; ``field`` is that of the
    side ``inside``. Without, ``field`` answers every camera as it dispatches them.
    """

    def __init__(self, field: VisibilityField, index: np.ndarray, world: np.ndarray,
                 encode: Callable[[bool], VisibilityField] | None = None, inside: bool | None = None):
        n = field.num_points
        order = np.arange(n)
        self._rank = field.rank
        if field.rank is not None:  # stored row rank[i] holds the field's point i
            order[field.rank.cpu().numpy()] = np.arange(n)
        self._order = None if field.rank is None else torch.from_numpy(order).to(field.device)
        self._encode, self._lock, self._frame = encode, threading.Lock(), field.frame
        self._fields = {inside if encode is not None else None: self._stored(field)}
        self.index = index[order]
        world = np.ascontiguousarray(world[order])
        self.world = torch.from_numpy(world)
        self.block = max(_BLOCK, -(-n // _MAX_BLOCKS))
        padded = np.concatenate([world, np.repeat(world[-1:], -n % self.block, axis=0)]).reshape(-1, self.block, 3)
        self.lo, self.hi = padded.min(axis=1), padded.max(axis=1)

    def _stored(self, field: VisibilityField) -> VisibilityField:
        """``field`` with its points in the order it stores them (the tile's)."""
        if (field.rank is None) != (self._rank is None) or (field.rank is not None and not torch.equal(
                field.rank, self._rank)):
            raise RuntimeError("the encodings of the two sides of a crop store its points in different orders")
        return field if self._order is None else field.restricted(self._order)

    def field_for(self, location: torch.Tensor) -> VisibilityField:
        """The field, over the tile's points in its order, that answers a camera at ``location``
        (encoded on the first camera of its side; thread-safe); without ``encode``, the one field,
        whose queries go to its scene field where they should."""
        if self._encode is None:
            return self._fields[None]
        inside = bool(self._frame.contains(location[None])[0])
        with self._lock:
            if inside not in self._fields:
                self._fields[inside] = self._stored(self._encode(inside))
            return self._fields[inside]

    def blocks(self, view: PinholeView, max_range: float | None) -> tuple[np.ndarray, np.ndarray]:
        """The blocks that may hold points of the frame (not wholly outside one of the image's sides
        or behind the camera, nor farther than ``max_range``) and, of those, the ones wholly inside."""
        rotation, shift = view.extrinsic[:3, :3], view.extrinsic[:3, 3]
        k, w, h = view.intrinsic, view.width, view.height
        # half-spaces n . x >= 0 of camera coordinates: the image's four sides and the front
        sides = np.array([[k[0, 0], k[0, 1], k[0, 2] + 0.5], [-k[0, 0], -k[0, 1], w - 0.5 - k[0, 2]],
                          [0.0, k[1, 1], k[1, 2] + 0.5], [0.0, -k[1, 1], h - 0.5 - k[1, 2]], [0.0, 0.0, 1.0]])
        normals, offsets = sides @ rotation, sides @ shift  # the same half-spaces in world coordinates
        ahead = normals[:, None, :] > 0  # a box's corner farthest along each normal, and nearest
        farthest = np.einsum("pbi,pi->pb", np.where(ahead, self.hi[None], self.lo[None]), normals) + offsets[:, None]
        nearest = np.einsum("pbi,pi->pb", np.where(ahead, self.lo[None], self.hi[None]), normals) + offsets[:, None]
        keep, inside = (farthest >= 0).all(axis=0), (nearest > 0).all(axis=0)
        if max_range is not None:
            location = view.location
            gap = np.clip(location, self.lo, self.hi) - location
            reach = np.maximum(np.abs(self.lo - location), np.abs(self.hi - location))
            keep &= np.einsum("bi,bi->b", gap, gap) <= max_range * max_range
            inside &= np.einsum("bi,bi->b", reach, reach) <= max_range * max_range
        return np.flatnonzero(keep), inside

    def crop(self, view: PinholeView, max_range: float | None) -> torch.Tensor:
        """The stored rows, ascending, of the points the frame sees (in its image, in front of the
        camera, within ``max_range``), as :meth:`~o3dvis.cameras.Frustum.contains` tells them (the
        points of a block wholly inside without a test of their own)."""
        blocks, inside = self.blocks(view, max_range)
        rows = (blocks[:, None] * self.block + np.arange(self.block)).ravel()
        whole = np.repeat(inside[blocks], self.block)
        if len(blocks) and blocks[-1] == len(self.lo) - 1:  # the last block's padding
            real = rows < len(self.world)
            rows, whole = rows[real], whole[real]
        rows, keep = torch.from_numpy(rows), torch.from_numpy(whole)
        tested = (~keep).nonzero()[:, 0]
        if len(tested):
            pixels, depth, cam = self.project(view, rows[tested])
            seen = (depth > 0) & (pixels >= -0.5).all(dim=1) & (pixels[:, 0] < view.width - 0.5)
            seen &= pixels[:, 1] < view.height - 0.5
            if max_range is not None:
                seen &= cam.square().sum(dim=1) <= max_range * max_range
            keep[tested] = seen
        return rows[keep]

    def project(self, view: PinholeView, rows: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``((M, 2) pixels (u, v), (M,) depths, (M, 3) camera coordinates)`` of the stored ``rows``,
        in float64 (the pixels of points at or behind the camera are meaningless)."""
        k = view.intrinsic
        cam = torch.addmm(torch.from_numpy(view.extrinsic[:3, 3].copy()), self.world.index_select(0, rows),
                          torch.from_numpy(view.extrinsic[:3, :3].T.copy()))
        x, y, depth = cam.unbind(1)
        inverse = torch.where(depth > 0, depth, 1.0).reciprocal_()
        v = y * inverse
        u = (x * inverse).mul_(k[0, 0]).add_(v, alpha=k[0, 1]).add_(k[0, 2])
        return torch.stack([u, v.mul_(k[1, 1]).add_(k[1, 2])], dim=1), depth, cam

    def frame(self, view: PinholeView, max_range: float | None, threshold: float, images: bool) -> Frame:
        """What ``view`` sees of this tile's points (see :func:`visible_in_frame`)."""
        # the torch ops here on the threads the load allows, as the query's own
        with torch_threads(plan_threads(len(self.world), _SPLIT_ROWS)):
            rows = self.crop(view, max_range)
            if len(rows):
                location = torch.from_numpy(view.location)
                field = self.field_for(location)
                field = field.restricted(rows.to(field.device))
                seen = torch.from_numpy(field.query(Views(location[None], None, (None,)), threshold=threshold,
                                                    frustum=False)[0])
                rows = rows[seen]
            indices, ascending = torch.from_numpy(self.index).index_select(0, rows).sort()
            pixels, depths, _ = self.project(view, rows[ascending])
            indices, pixels, depths = indices.numpy(), pixels.numpy(), depths.float().numpy()
            pictures = frame_images(indices, pixels, depths, view.width, view.height) if images else (None, None)
        return Frame(indices, pixels.astype(np.float32), depths, *pictures)


def frame_images(indices: np.ndarray, pixels: np.ndarray, depths: np.ndarray, width: int, height: int
            ) -> tuple[np.ndarray, np.ndarray]:
    """The depth and index images of a frame's visible points: each pixel shows the nearest of the
    points whose (float64) pixel coordinates round to it (of equals, the one of smallest index)."""
    cell = np.floor(pixels + 0.5).astype(np.int64)
    np.clip(cell, 0, [width - 1, height - 1], out=cell)  # a point within rounding of the image's border
    flat = torch.from_numpy(cell[:, 1] * width + cell[:, 0])
    depth = torch.from_numpy(depths)
    nearest = torch.full((width * height,), torch.inf).scatter_reduce_(0, flat, depth, "amin")
    front = depth == nearest[flat]
    index = torch.full((width * height,), torch.iinfo(torch.int64).max).scatter_reduce_(
        0, flat[front], torch.from_numpy(indices)[front], "amin")
    empty = torch.isinf(nearest)
    return (nearest.masked_fill_(empty, 0).view(height, width).numpy(),
            index.masked_fill_(empty, -1).view(height, width).numpy())


def empty_frame(view: PinholeView, images: bool) -> Frame:
    """A frame that sees no point."""
    none = np.zeros(0, dtype=np.int64)
    pictures = frame_images(none, np.zeros((0, 2)), np.zeros(0, dtype=np.float32), view.width, view.height) \
        if images else (None, None)
    return Frame(none, np.zeros((0, 2), dtype=np.float32), np.zeros(0, dtype=np.float32), *pictures)
