"""Pictures of scenes: point clouds and grasp candidates in 3-D (matplotlib)."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

from rtv3_maniskill import se3  # noqa: E402

FINGER_LENGTH = 0.045
PALM_OFFSET = 0.06


def gripper_lines(pose: np.ndarray, width: float) -> list[np.ndarray]:
    """Polylines ``(k, 3)`` sketching a parallel-jaw gripper at TCP pose ``(4, 4)`` (world)."""
    half = width / 2 + 0.005
    local = [
        np.array([[0, -half, -FINGER_LENGTH], [0, half, -FINGER_LENGTH]]),  # palm bar
        np.array([[0, -half, -FINGER_LENGTH], [0, -half, 0.0]]),  # finger
        np.array([[0, half, -FINGER_LENGTH], [0, half, 0.0]]),  # finger
        np.array([[0, 0, -FINGER_LENGTH], [0, 0, -FINGER_LENGTH - PALM_OFFSET]]),  # wrist
    ]
    return [seg @ pose[:3, :3].T + pose[:3, 3] for seg in local]


def plot_point_cloud_and_grasps(
    ax,
    points: np.ndarray,
    grasp_poses: np.ndarray,
    grasp_widths: np.ndarray,
    target: int | None = None,
    trajectory: np.ndarray | None = None,
) -> None:
    """Draw ``points (N, 6)`` xyz+rgb, grasps ``(M, 4, 4)`` (target in red) and an optional
    TCP ``trajectory (S, 3)`` on a 3-D axis; world frame, metres."""
    if len(points):
        ax.scatter(points[:, 0], points[:, 1], points[:, 2], c=np.clip(points[:, 3:6], 0, 1), s=2, depthshade=False)
    for i, (pose, width) in enumerate(zip(grasp_poses, grasp_widths)):
        is_target = target is not None and i == target
        for line in gripper_lines(pose, float(width)):
            ax.plot(*line.T, color="red" if is_target else "tab:green", lw=2.0 if is_target else 0.6,
                    alpha=1.0 if is_target else 0.6)
    if trajectory is not None and len(trajectory):
        ax.plot(*trajectory.T, color="black", lw=1.5)
        ax.scatter(*trajectory[0], color="black", s=20, marker="o")
    span = np.concatenate([points[:, :3], grasp_poses[:, :3, 3]]) if len(points) else grasp_poses[:, :3, 3]
    if trajectory is not None and len(trajectory):
        span = np.concatenate([span, trajectory])
    centre = (span.max(0) + span.min(0)) / 2
    radius = max(float((span.max(0) - span.min(0)).max()) / 2, 0.05)
    ax.set_xlim(centre[0] - radius, centre[0] + radius)
    ax.set_ylim(centre[1] - radius, centre[1] + radius)
    ax.set_zlim(max(centre[2] - radius, -0.01), centre[2] + radius)
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_zlabel("z [m]")


def grasp_array_to_poses(grasps: np.ndarray) -> np.ndarray:
    """``(M, 9)`` [pos, quat wxyz, width, score] -> ``(M, 4, 4)``."""
    g = torch.as_tensor(grasps, dtype=torch.float64)
    return se3.pose_to_matrix(g[:, :3], g[:, 3:7]).numpy()


def save_scene_figure(path, image: np.ndarray, points: np.ndarray, grasps: np.ndarray, target: int | None,
                      title: str) -> None:
    """A two-panel PNG: the rendered scene, and the point cloud with the grasp candidates."""
    fig = plt.figure(figsize=(12, 5.5))
    ax_img = fig.add_subplot(1, 2, 1)
    ax_img.imshow(image)
    ax_img.set_axis_off()
    ax_img.set_title("rendered scene")
    ax3d = fig.add_subplot(1, 2, 2, projection="3d")
    plot_point_cloud_and_grasps(ax3d, points, grasp_array_to_poses(grasps), grasps[:, 7], target)
    ax3d.set_title(f"point cloud ({len(points)} pts) and {len(grasps)} grasp candidates (target red)")
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
