"""ChArUco board views seen by a known camera (with its lens distortion): calibration test data."""

from __future__ import annotations

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


def render_charuco_views(
    camera: CameraModel,
    board: cv2.aruco.CharucoBoard,
    poses: list[tuple[Rotation, np.ndarray]],
    noise_sigma: float = 1.5,
    seed: int = 0,
) -> list[np.ndarray]:
    """Gray images of the printed board (white paper margin) at each pose, through the lens."""
    rng = np.random.default_rng(seed)
    dmap = build_distortion_map(camera)
    cw, ch = dmap.canvas_size
    backdrop = background_panorama(ch, camera.fx, rng)[:, :cw]
    cols, rows = board.getChessboardSize()
    sq = board.getSquareLength()
    images = []
    for rot, t in poses:
        r = rot.as_matrix()
        # Texture resolution about the on-screen square size: neither aliasing nor wasted work.
        depth = float(t[2] + r[2, :2] @ (np.array([cols, rows]) * sq / 2))
        sq_px = int(np.clip(np.ceil(camera.fx * sq / max(depth, 0.1) * 1.5), 24, 256))
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
        canvas = backdrop.copy()
        cv2.warpPerspective(
            tex, h, (cw, ch), dst=canvas, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_TRANSPARENT
        )
        img = cv2.remap(
            canvas, dmap.map1, dmap.map2, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
        )
        if noise_sigma > 0:
            img = cv2.add(
                img, rng.normal(0, noise_sigma, np.shape(img)).astype(np.float32), dtype=cv2.CV_8U
            )
        images.append(img)
    return images
