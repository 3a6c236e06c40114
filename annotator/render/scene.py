"""The marker room as geometry: which markers a camera sees and how they land on its canvas.

Poses here are R_world_camera (3x3) and the camera centre in world metres; OpenCV camera frame
(x right, y down, z forward). Marker frame: x right, y up, z out of the face.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from annotator.render.camera import CameraModel
from annotator.render.textures import MARKER_CELLS, QUIET_CELLS, MarkerTextures
from bgt_core.formats.markers import MarkerPose

NEAR_M = 0.2  # closer than this to the image plane a marker is not drawn (and not expected)
MIN_FACING_COS = 0.2  # seen more obliquely than ~78 degrees: skipped


def square_corners(half: float) -> np.ndarray:
    """Marker-frame corners in ArUco order: top-left, top-right, bottom-right, bottom-left."""
    return np.array(
        [[-half, half, 0.0], [half, half, 0.0], [half, -half, 0.0], [-half, -half, 0.0]]
    )


@dataclass(frozen=True)
class PlacedMarker:
    id: int
    rotation: np.ndarray  # marker -> world, 3x3
    centre: np.ndarray  # world, metres
    gain: float  # print/lighting brightness factor
    scale: float = 1.0  # printed side / the nominal length (a printer's scaling)


PILLAR_HEIGHT = 3.0  # floor to ceiling, metres
PILLAR_MAX_HALF = 0.6  # a pillar's markers sit at most this far from its axis


@dataclass(frozen=True)
class PillarFace:
    """One vertical face of a square pillar carrying a marker: it hides what is behind it."""

    marker_id: int
    corners: np.ndarray  # (4, 3) world, floor to PILLAR_HEIGHT, convex order
    normal: np.ndarray  # horizontal, outwards
    centre: np.ndarray
    shade: int  # gray level, by direction, so two visible faces differ


def find_pillar_faces(markers: list[PlacedMarker]) -> dict[int, PillarFace]:
    """Four markers around a common vertical axis, each facing away from it, are taken as the
    four faces of a square pillar (as in the tetam room); other markers hang on walls."""
    faces: dict[int, PillarFace] = {}
    for m in markers:
        if m.id in faces:
            continue
        group = [
            o for o in markers if np.linalg.norm(o.centre[:2] - m.centre[:2]) < 2 * PILLAR_MAX_HALF
        ]
        if len(group) != 4:
            continue
        axis = np.mean([o.centre[:2] for o in group], axis=0)
        normals = [o.rotation[:2, 2] / max(np.linalg.norm(o.rotation[:2, 2]), 1e-9) for o in group]
        offsets = [float(n @ (o.centre[:2] - axis)) for n, o in zip(normals, group, strict=True)]
        if min(offsets) <= 0.05 or max(offsets) > PILLAR_MAX_HALF:
            continue
        half = float(np.mean(offsets))
        for o, n in zip(group, normals, strict=True):
            along = np.array([-n[1], n[0], 0.0])  # horizontal, in the face
            base = np.array([o.centre[0], o.centre[1], 0.0])
            up = np.array([0.0, 0.0, PILLAR_HEIGHT])
            corners = np.array(
                [
                    base - half * along,
                    base + half * along,
                    base + half * along + up,
                    base - half * along + up,
                ]
            )
            normal = np.array([n[0], n[1], 0.0])
            faces[o.id] = PillarFace(
                o.id, corners, normal, corners.mean(axis=0), int(100 + 45 * abs(n[0]))
            )
    return faces


def clip_near(poly: np.ndarray, near: float = NEAR_M) -> np.ndarray:
    """Camera-frame polygon (N, 3) cut to the part with z >= near (Sutherland-Hodgman)."""
    out = []
    n = len(poly)
    for i in range(n):
        a, b = poly[i], poly[(i + 1) % n]
        a_in, b_in = a[2] >= near, b[2] >= near
        if a_in:
            out.append(a)
        if a_in != b_in:
            f = (near - a[2]) / (b[2] - a[2])
            out.append(a + f * (b - a))
    return np.array(out).reshape(-1, 3)


class MarkerScene:
    """The site's markers with their printed size (and the pillars some of them are fixed to);
    draws them onto a pinhole canvas. ``scales`` (marker id -> printed side / ``length``) prints
    markers larger or smaller than the nominal length says; absent ids are exact."""

    def __init__(
        self, markers: dict[int, MarkerPose], length: float, scales: dict[int, float] | None = None
    ) -> None:
        self.length = float(length)
        self.markers = [
            PlacedMarker(
                m.id,
                Rotation.from_euler("xyz", m.euler_xyz).as_matrix(),
                np.array(m.position, float),
                float(np.random.default_rng(1000 + m.id).uniform(0.75, 1.0)),
                float((scales or {}).get(m.id, 1.0)),
            )
            for m in sorted(markers.values(), key=lambda m: m.id)
        ]
        cell = self.length / MARKER_CELLS
        self.half_outer = self.length / 2 + QUIET_CELLS * cell
        self.inner = square_corners(self.length / 2)
        self.outer = square_corners(self.half_outer)
        self.pillar_faces = find_pillar_faces(self.markers)

    def _facing(self, m: PlacedMarker, centre_w: np.ndarray) -> bool:
        view = centre_w - m.centre
        dist = float(np.linalg.norm(view))
        return dist > 1e-9 and float(m.rotation[:, 2] @ view) > MIN_FACING_COS * dist

    def corners_camera(
        self, m: PlacedMarker, r_wc: np.ndarray, c_w: np.ndarray, corners: np.ndarray
    ) -> np.ndarray:
        """Marker-frame points of the nominal sheet -> camera frame, as printed (scaled)."""
        world = m.centre + (m.scale * corners) @ m.rotation.T
        return (world - c_w) @ r_wc

    def visible(self, r_wc: np.ndarray, c_w: np.ndarray) -> list[PlacedMarker]:
        """Markers facing the camera with the whole printed sheet in front of the near plane,
        farthest first (the order to paint them in, so nearer sheets cover farther ones)."""
        out = []
        for m in self.markers:
            if not self._facing(m, c_w):
                continue
            if np.all(self.corners_camera(m, r_wc, c_w, self.outer)[:, 2] > NEAR_M):
                out.append(m)
        return sorted(out, key=lambda m: -float(np.linalg.norm(m.centre - c_w)))

    def paint_order(
        self, r_wc: np.ndarray, c_w: np.ndarray
    ) -> list[PlacedMarker | tuple[PillarFace, np.ndarray]]:
        """Markers and (pillar face, its camera-frame polygon cut at the near plane), farthest
        first; a marker on a pillar comes right after its face."""
        items: list[tuple[float, int, PlacedMarker | tuple[PillarFace, np.ndarray]]] = []
        for face in self.pillar_faces.values():
            if float(face.normal @ (c_w - face.centre)) <= 0:
                continue
            poly = clip_near((face.corners - c_w) @ r_wc)
            if len(poly) >= 3:
                items.append((float(np.linalg.norm(face.centre - c_w)), 0, (face, poly)))
        for m in self.visible(r_wc, c_w):
            on_face = self.pillar_faces.get(m.id)
            key = float(np.linalg.norm((on_face.centre if on_face else m.centre) - c_w))
            items.append((key, 1, m))
        items.sort(key=lambda it: (-it[0], it[1]))
        return [it[2] for it in items]

    def draw(
        self,
        canvas: np.ndarray,
        canvas_k: np.ndarray,
        r_wc: np.ndarray,
        c_w: np.ndarray,
        textures: MarkerTextures,
        order: list[PlacedMarker | tuple[PillarFace, np.ndarray]] | None = None,
    ) -> list[int]:
        """Paste every visible marker onto the gray canvas in place; returns the ids drawn.

        `order` (from `paint_order` at a nearby pose) saves working out visibility again: the
        rolling-shutter renderer draws one frame as bands at slightly different poses.
        """
        h_img, w_img = canvas.shape[:2]
        drawn = []
        cells = textures.cells_total()
        for item in self.paint_order(r_wc, c_w) if order is None else order:
            if not isinstance(item, PlacedMarker):
                face = item[0]
                poly = item[1] if order is None else clip_near((face.corners - c_w) @ r_wc)
                if len(poly) < 3:
                    continue
                uv = (poly @ canvas_k.T)[:, :2] / poly[:, 2:3]
                cv2.fillConvexPoly(
                    canvas,
                    np.round(uv * 16).astype(np.int32),
                    face.shade,
                    lineType=cv2.LINE_AA,
                    shift=4,
                )
                continue
            m = item
            outer_c = self.corners_camera(m, r_wc, c_w, self.outer)
            uv = (outer_c @ canvas_k.T)[:, :2] / outer_c[:, 2:3]
            x0, y0 = np.floor(uv.min(axis=0)).astype(int) - 1
            x1, y1 = np.ceil(uv.max(axis=0)).astype(int) + 2
            x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, w_img), min(y1, h_img)
            if x1 <= x0 or y1 <= y0:
                continue
            side_px = float(np.max(np.linalg.norm(np.roll(uv, -1, axis=0) - uv, axis=1)))
            level = textures.level_for(side_px * MARKER_CELLS / cells)
            tex = textures.get(m.id, level, m.gain)
            size = tex.shape[0]
            # texture pixel (u, v) -> marker plane (x, y): pixel centres at integers, edges at -0.5.
            half = self.half_outer * m.scale
            s = 2 * half / size
            tex_to_plane = np.array(
                [
                    [s, 0.0, -half + 0.5 * s],
                    [0.0, -s, half - 0.5 * s],
                    [0.0, 0.0, 1.0],
                ]
            )
            r_cm = r_wc.T @ m.rotation
            t_cm = r_wc.T @ (m.centre - c_w)
            plane_to_img = canvas_k @ np.column_stack([r_cm[:, 0], r_cm[:, 1], t_cm])
            shift = np.array([[1.0, 0.0, -x0], [0.0, 1.0, -y0], [0.0, 0.0, 1.0]])
            h = shift @ plane_to_img @ tex_to_plane
            roi = np.ascontiguousarray(canvas[y0:y1, x0:x1])
            cv2.warpPerspective(
                tex,
                h,
                (x1 - x0, y1 - y0),
                dst=roi,
                flags=cv2.INTER_LINEAR,
                borderMode=cv2.BORDER_TRANSPARENT,
            )
            canvas[y0:y1, x0:x1] = roi
            drawn.append(m.id)
        return drawn

    def expected_corners(
        self, cam: CameraModel, r_wc: np.ndarray, c_w: np.ndarray, margin: float = 2.0
    ) -> dict[int, np.ndarray]:
        """Distorted pixel corners (4,2) of each drawn marker lying wholly inside the image and
        not overlapped by a nearer marker's sheet."""
        out = {}
        order = self.paint_order(r_wc, c_w)
        sheets = [
            cam.project(
                self.corners_camera(it, r_wc, c_w, self.outer)
                if isinstance(it, PlacedMarker)
                else it[1]
            ).astype(np.float32)
            for it in order
        ]
        for i, m in enumerate(order):
            if not isinstance(m, PlacedMarker):
                continue
            outer = sheets[i]
            inside = (
                (outer[:, 0] >= margin)
                & (outer[:, 0] <= cam.width - 1 - margin)
                & (outer[:, 1] >= margin)
                & (outer[:, 1] <= cam.height - 1 - margin)
            )
            if not inside.all():
                continue
            # Farthest first: everything later is painted over this marker.
            if any(cv2.intersectConvexConvex(outer, nearer)[0] > 0 for nearer in sheets[i + 1 :]):
                continue
            out[m.id] = cam.project(self.corners_camera(m, r_wc, c_w, self.inner))
        return out
