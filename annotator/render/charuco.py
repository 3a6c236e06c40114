"""ChArUco board views seen by a known camera (with its lens distortion): calibration test data."""

from __future__ import annotations

from collections.abc import Callable

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from annotator.render.camera import CameraModel, build_distortion_map
from annotator.render.textures import aruco_dictionary, background_panorama


def charuco_board(
    squares: tuple[int, int], square_length: float, marker_length: float, dictionary: str
) -> cv2.aruco.CharucoBoard:
    """squares = (columns, rows); lengths in metres."""
    return cv2.aruco.CharucoBoard(
        squares, square_length, marker_length, aruco_dictionary(dictionary)
    )


def random_board_poses(
    n: int, board: cv2.aruco.CharucoBoard, camera: CameraModel, rng: np.random.Generator
) -> list[tuple[Rotation, np.ndarray]]:
    """Board->camera poses (R_cam_board, t_cam_board) at 0.45-0.9 m, tilted up to ~40 degrees,
    spread over the picture so the distortion is observed towards the edges too."""
    cols, rows = board.getChessboardSize()
    size = np.array([cols, rows]) * board.getSquareLength()
    poses: list[tuple[Rotation, np.ndarray]] = []
    while len(poses) < n:
        dist = rng.uniform(0.45, 0.9)
        # Aim the board centre at a random point in the central 70 % of the picture.
        u = rng.uniform(0.15, 0.85) * camera.width
        v = rng.uniform(0.15, 0.85) * camera.height
        centre = dist * np.array([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, 1.0])
        axis = rng.normal(size=2)
        tilt = Rotation.from_rotvec(
            np.append(axis / np.linalg.norm(axis), 0.0) * np.radians(rng.uniform(10, 40))
        )
        rot = tilt * Rotation.from_euler("z", rng.uniform(-25, 25), degrees=True)
        t = centre - rot.apply(np.append(size / 2, 0.0))
        corners = np.array(
            [[0, 0, 0], [size[0], 0, 0], [size[0], size[1], 0], [0, size[1], 0]], float
        )
        cam_pts = rot.apply(corners) + t
        if cam_pts[:, 2].min() < 0.2:
            continue
        uv = camera.project(cam_pts)
        if uv.min() < 5 or uv[:, 0].max() > camera.width - 6 or uv[:, 1].max() > camera.height - 6:
            continue  # the whole board in view: partial views are fine for OpenCV but not needed here
        poses.append((rot, t))
    return poses


class BoardPainter:
    """Draws the printed board (white paper margin) into a camera's undistorted canvas."""

    def __init__(
        self, camera: CameraModel, board: cv2.aruco.CharucoBoard, rng: np.random.Generator
    ) -> None:
        self.board = board
        self.dmap = build_distortion_map(camera)
        cw, ch = self.dmap.canvas_size
        self.backdrop = background_panorama(ch, camera.fx, rng)[:, :cw]
        self.fx = camera.fx

    def canvas(self, rot: Rotation, t: np.ndarray) -> np.ndarray:
        board, dmap = self.board, self.dmap
        cols, rows = board.getChessboardSize()
        sq = board.getSquareLength()
        r = rot.as_matrix()
        # Texture resolution about the on-screen square size: neither aliasing nor wasted work.
        depth = float(t[2] + r[2, :2] @ (np.array([cols, rows]) * sq / 2))
        sq_px = int(np.clip(np.ceil(self.fx * sq / max(depth, 0.1) * 1.5), 24, 256))
        margin = sq_px // 2
        tex = board.generateImage((cols * sq_px, rows * sq_px), marginSize=0)
        tex = cv2.copyMakeBorder(
            tex, margin, margin, margin, margin, cv2.BORDER_CONSTANT, value=255
        )
        tex = (30 + tex.astype(np.float32) * (200 / 255)).astype(np.uint8)
        s = sq / sq_px
        tex_to_board = np.array(
            [[s, 0, (0.5 - margin) * s], [0, s, (0.5 - margin) * s], [0, 0, 1.0]]
        )
        h = dmap.canvas_K @ np.column_stack([r[:, 0], r[:, 1], t]) @ tex_to_board
        canvas = self.backdrop.copy()
        cw, ch = dmap.canvas_size
        cv2.warpPerspective(
            tex, h, (cw, ch), dst=canvas, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_TRANSPARENT
        )
        return canvas

    def image(self, canvas: np.ndarray, rows: slice = slice(None)) -> np.ndarray:
        """Output rows ``rows`` of the distorted picture of ``canvas``."""
        return cv2.remap(
            canvas,
            self.dmap.map1[rows],
            self.dmap.map2[rows],
            cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_REPLICATE,
        )


def _add_noise(img: np.ndarray, sigma: float, rng: np.random.Generator) -> np.ndarray:
    if sigma <= 0:
        return img
    return cv2.add(img, rng.normal(0, sigma, np.shape(img)).astype(np.float32), dtype=cv2.CV_8U)


def render_charuco_views(
    camera: CameraModel,
    board: cv2.aruco.CharucoBoard,
    poses: list[tuple[Rotation, np.ndarray]],
    noise_sigma: float = 1.5,
    seed: int = 0,
) -> list[np.ndarray]:
    """Gray images of the printed board (white paper margin) at each pose, through the lens."""
    rng = np.random.default_rng(seed)
    painter = BoardPainter(camera, board, rng)
    return [_add_noise(painter.image(painter.canvas(rot, t)), noise_sigma, rng) for rot, t in poses]


def waving_board(
    board: cv2.aruco.CharucoBoard, distance: float = 0.7, rate_deg_s: float = 90.0, seed: int = 0
) -> Callable[[float], tuple[Rotation, np.ndarray]]:
    """A board held ``distance`` m in front of the camera and waved: turned about its vertical
    and horizontal axes (peak angular speed about ``rate_deg_s``) and swayed a few cm, as a
    person moves it for a readout calibration. Returns pose(t) = (R_cam_board, t_cam_board)."""
    rng = np.random.default_rng(seed)
    cols, rows = board.getChessboardSize()
    half = np.array([cols, rows, 0.0]) * board.getSquareLength() / 2
    f1, f2 = rng.uniform(0.5, 0.8), rng.uniform(0.4, 0.7)
    p1, p2 = rng.uniform(0, 2 * np.pi, 2)
    a1 = np.radians(rate_deg_s) / (2 * np.pi * f1)
    a2 = 0.6 * np.radians(rate_deg_s) / (2 * np.pi * f2)

    def pose(t: float) -> tuple[Rotation, np.ndarray]:
        rot = Rotation.from_euler(
            "yxz",
            [a1 * np.sin(2 * np.pi * f1 * t + p1), a2 * np.sin(2 * np.pi * f2 * t + p2), 0.1],
        )
        centre = np.array([0.04 * np.sin(2 * np.pi * 0.3 * t), 0.03 * np.sin(1.7 * t), distance])
        return rot, centre - rot.apply(half)

    return pose


def render_charuco_video(
    path: str,
    camera: CameraModel,
    board: cv2.aruco.CharucoBoard,
    pose_at: Callable[[float], tuple[Rotation, np.ndarray]],
    times: np.ndarray,
    readout: float,
    noise_sigma: float = 1.5,
    seed: int = 0,
    bands: int = 40,
) -> int:
    """A video (mp4v) of the board moving by ``pose_at``, frames stamped ``times``, through a
    rolling shutter: output rows are drawn in ``bands`` strips, each from the pose at its middle
    row's time (``t + readout * v / height``). Returns the frames written."""
    from annotator.core.rolling_shutter import row_delay

    rng = np.random.default_rng(seed)
    painter = BoardPainter(camera, board, rng)
    edges = np.round(np.linspace(0, camera.height, bands + 1)).astype(int)
    mids = row_delay((edges[:-1] + edges[1:] - 1) / 2, camera.height, readout)
    fps = 1.0 / float(np.median(np.diff(times))) if len(times) > 1 else 30.0
    size = (camera.width, camera.height)
    writer = cv2.VideoWriter(path, cv2.VideoWriter.fourcc(*"mp4v"), fps, size)
    if not writer.isOpened():
        raise OSError(f"cannot open a video writer for {path} (mp4v)")
    try:
        for t in times:
            img = np.empty((camera.height, camera.width), np.uint8)
            for b in range(bands):
                rows = slice(int(edges[b]), int(edges[b + 1]))
                img[rows] = painter.image(painter.canvas(*pose_at(float(t) + mids[b])), rows)
            writer.write(cv2.cvtColor(_add_noise(img, noise_sigma, rng), cv2.COLOR_GRAY2BGR))
    finally:
        writer.release()
    return len(times)
