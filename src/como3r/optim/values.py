"""The variables of a pose solve: Sim(3) poses, some of them pinned.

``PoseValues`` plays the role of GTSAM's ``Values``: it holds the current estimate and
knows how to move it along a tangent step, and nothing else. Factors read poses from it;
optimizers produce steps for it.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from como3r.errors import InputError
from como3r.geometry.lie import sim3_normalize, sim3_retract

POSE_DIM = 8
TANGENT_DIM = 7


@dataclass(frozen=True, eq=False)
class PoseValues:
    """Sim(3) poses ``T_WC`` of N keyframes (or frames) and which of them are held fixed.

    Attributes:
        poses: ``(N, 8)`` poses ``T_WC`` = translation (3), quaternion xyzw (4), scale (1).
        pinned: ``(N,)`` bool; a pinned pose is a constant of the solve (the gauge anchor
            of C-Sec. A.3, the keyframe of a tracking problem).
    """

    poses: torch.Tensor
    pinned: torch.Tensor

    def __post_init__(self) -> None:
        if not isinstance(self.poses, torch.Tensor) or self.poses.ndim != 2:
            raise InputError(
                f"PoseValues: poses must be an (N, 8) tensor, got {_shape(self.poses)}"
            )
        if self.poses.shape[-1] != POSE_DIM or not self.poses.is_floating_point():
            raise InputError(
                f"PoseValues: poses must be a floating (N, 8) tensor, got {_shape(self.poses)}"
            )
        if not isinstance(self.pinned, torch.Tensor) or self.pinned.shape != self.poses.shape[:1]:
            raise InputError(
                f"PoseValues: pinned must be a bool tensor of shape ({len(self.poses)},), "
                f"got {_shape(self.pinned)}"
            )
        if self.pinned.dtype != torch.bool:
            raise InputError(f"PoseValues: pinned must be a bool tensor, got {self.pinned.dtype}")
        if self.pinned.device != self.poses.device:
            raise InputError("PoseValues: poses and pinned must be on the same device")

    @classmethod
    def from_poses(cls, poses: torch.Tensor, num_pinned: int = 1) -> PoseValues:
        """Poses ``(N, 8)`` with the first ``num_pinned`` of them pinned (C-Tab. 3, "pin 1")."""
        if not isinstance(poses, torch.Tensor):
            raise InputError(f"PoseValues: poses must be an (N, 8) tensor, got {type(poses)}")
        if num_pinned < 0:
            raise InputError(f"PoseValues: num_pinned must be >= 0, got {num_pinned}")
        pinned = torch.arange(poses.shape[0], device=poses.device) < num_pinned
        return cls(poses, pinned)

    @property
    def num_poses(self) -> int:
        """N, the number of poses (pinned ones included)."""
        return self.poses.shape[0]

    @property
    def free(self) -> torch.Tensor:
        """``(N,)`` bool mask of the poses a solve may move."""
        return ~self.pinned

    @property
    def num_free(self) -> int:
        """The number of poses a solve may move."""
        return int(self.free.sum())

    def retract(self, tau: torch.Tensor) -> PoseValues:
        """Left retraction ``T_k <- Exp(tau_k) T_k`` of every free pose (C-Eq. 25).

        Args:
            tau: ``(N, 7)`` tangent step ``(v, omega, zeta)`` per pose; rows of pinned poses
                are ignored, so a pinned pose keeps its exact value.

        Returns:
            New ``PoseValues`` with the same pinned mask.
        """
        if tau.shape != (self.num_poses, TANGENT_DIM):
            raise InputError(
                f"PoseValues.retract: tau must have shape ({self.num_poses}, 7), got {_shape(tau)}"
            )
        # Re-normalising keeps the quaternions unit over hundreds of solver iterations.
        moved = sim3_normalize(sim3_retract(tau.to(self.poses), self.poses))
        poses = torch.where(self.pinned[:, None], self.poses, moved)
        return PoseValues(poses, self.pinned)


def _shape(value: object) -> str:
    """Shape of a tensor (or the type of anything else) for error messages."""
    if isinstance(value, torch.Tensor):
        return f"shape {tuple(value.shape)}"
    return f"a {type(value).__name__}"
