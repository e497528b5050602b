"""A ROS transform tree (tf2_msgs/TFMessage from /tf and /tf_static) and the chains through it.

Each `geometry_msgs/TransformStamped` is an edge parent (`header.frame_id`) → child (`child_frame_id`) holding
T_parent_child, as tf2 does: every frame has at most one parent, so two frames meet at their nearest common ancestor.
Static edges hold one transform; dynamic edges a time series, evaluated between samples with translation linear and
rotation slerp, or at the sample nearest in time. Frame names lose a leading "/" (ROS 1 wrote "/base_link").
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from bimfactor.errors import InputError

log = logging.getLogger(__name__)


def frame_name(frame_id: str) -> str:
    """A tf frame id without the leading "/" that ROS 1 allowed."""
    return frame_id.strip().lstrip("/")


def stamp_ns(stamp: Any) -> int:
    """A builtin_interfaces/Time (ROS 1 times are read into the same type) in nanoseconds."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def transform_matrix(translation_xyz: np.ndarray, quaternion_xyzw: np.ndarray) -> np.ndarray:
    """(..., 3) translations and (..., 4) quaternions x, y, z, w (normalised here) → (..., 4, 4) rigid transforms."""
    t = np.asarray(translation_xyz, dtype=np.float64)
    q = np.asarray(quaternion_xyzw, dtype=np.float64)
    T = np.zeros((*t.shape[:-1], 4, 4))
    T[..., :3, :3] = Rotation.from_quat(q.reshape(-1, 4)).as_matrix().reshape(*t.shape[:-1], 3, 3)
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


def invert(T: np.ndarray) -> np.ndarray:
    """Inverse of (..., 4, 4) rigid transforms."""
    out = np.zeros_like(T)
    R_t = np.swapaxes(T[..., :3, :3], -1, -2)
    out[..., :3, :3] = R_t
    out[..., :3, 3] = -(R_t @ T[..., :3, 3, None])[..., 0]
    out[..., 3, 3] = 1.0
    return out


@dataclass
class _Edge:
    """T_parent_child: one static transform, or samples by stamp (one per stamp)."""

    parent: str
    static: bool
    stamps_ns: list[int] = field(default_factory=list)
    translations: list[tuple[float, float, float]] = field(default_factory=list)
    quaternions: list[tuple[float, float, float, float]] = field(default_factory=list)
    _arrays: tuple[np.ndarray, np.ndarray, np.ndarray, Slerp | None] | None = None

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, Slerp | None]:
        """(M,) sorted stamps, (M, 3) translations, (M, 4) quaternions and a Slerp over them (None for one sample)."""
        if self._arrays is None:
            stamps = np.array(self.stamps_ns, dtype=np.int64)
            order = np.argsort(stamps, kind="stable")
            stamps = stamps[order]
            keep = np.r_[stamps[1:] != stamps[:-1], True]  # of repeated stamps the one received last
            order, stamps = order[keep], stamps[keep]
            translations = np.array(self.translations, dtype=np.float64)[order]
            rotations = Rotation.from_quat(np.array(self.quaternions, dtype=np.float64)[order])
            slerp = Slerp((stamps - stamps[0]) / 1e9, rotations) if len(stamps) > 1 else None
            self._arrays = (stamps, translations, rotations.as_quat(), slerp)
        return self._arrays

    def at(self, t_ns: np.ndarray, *, nearest: bool) -> np.ndarray:
        """(N, 4, 4) T_parent_child at (N,) times: interpolated (NaN outside the samples' span) or the nearest one."""
        stamps, translations, quaternions, slerp = self.arrays()
        if self.static or (nearest and slerp is None):
            return np.broadcast_to(transform_matrix(translations[-1], quaternions[-1]), (len(t_ns), 4, 4)).copy()
        if nearest:
            right = np.clip(np.searchsorted(stamps, t_ns), 0, len(stamps) - 1)
            left = np.clip(right - 1, 0, len(stamps) - 1)
            pick = np.where(np.abs(stamps[left] - t_ns) <= np.abs(stamps[right] - t_ns), left, right)
            return transform_matrix(translations[pick], quaternions[pick])
        out = np.full((len(t_ns), 4, 4), np.nan)
        inside = (t_ns >= stamps[0]) & (t_ns <= stamps[-1])
        if slerp is None:
            out[inside] = transform_matrix(translations[0], quaternions[0])
        elif inside.any():
            s, s_samples = (t_ns[inside] - stamps[0]) / 1e9, (stamps - stamps[0]) / 1e9
            t = np.stack([np.interp(s, s_samples, translations[:, k]) for k in range(3)], axis=-1)
            out[inside] = transform_matrix(t, slerp(s).as_quat())
        return out


@dataclass(frozen=True)
class TfChain:
    """The edges from frame `target` to frame `source`: `steps` (child, parent, up) where `up` means the step goes
    from child to parent (the edge's transform is applied as is) and not up means the inverse."""

    target: str
    source: str
    steps: tuple[tuple[str, str, bool], ...]

    def frames(self) -> list[str]:
        """The frames along the chain, from `target` to `source`."""
        names = [self.target]
        for child, parent, up in self.steps:
            names.append(child if up else parent)
        return names


class TfTree:
    """The transforms of a recording's /tf_static and /tf, added message by message."""

    def __init__(self) -> None:
        self._edges: dict[str, _Edge] = {}  # by child frame
        self.frames_seen: set[str] = set()

    def add(self, msg: Any, *, static: bool) -> None:
        """Add the TransformStamped entries of a tf2_msgs/TFMessage; static ones replace earlier ones of the child."""
        for tf in msg.transforms:
            parent, child = frame_name(tf.header.frame_id), frame_name(tf.child_frame_id)
            if not parent or not child or parent == child:
                continue
            self.frames_seen.update((parent, child))
            edge = self._edges.get(child)
            if edge is not None and edge.static and static and edge.parent != parent:
                raise InputError(
                    f"tf: frame {child} has two parents on /tf_static, {edge.parent} and {parent} (a tf tree gives "
                    "each frame one); give --camera-mount x,y,z,roll,pitch,yaw"
                )
            if edge is not None and edge.static and not static:
                continue  # a mount published on /tf_static and again on /tf: the static one wins
            if edge is None or edge.parent != parent or edge.static != static:
                if edge is not None and edge.parent != parent:
                    log.warning("tf: frame %s moved from parent %s to %s; keeping the last", child, edge.parent, parent)
                edge = self._edges[child] = _Edge(parent, static)
            if static:
                edge.stamps_ns, edge.translations, edge.quaternions = [], [], []
            t, q = tf.transform.translation, tf.transform.rotation
            edge.stamps_ns.append(stamp_ns(tf.header.stamp))
            edge.translations.append((t.x, t.y, t.z))
            edge.quaternions.append((q.x, q.y, q.z, q.w))
            edge._arrays = None

    def __len__(self) -> int:
        return len(self._edges)

    def chain(self, target: str, source: str) -> TfChain | None:
        """The chain that gives T_target_source, or None when the two frames are not connected."""
        target, source = frame_name(target), frame_name(source)
        up_source = self._ancestors(source)
        up_target = self._ancestors(target)
        common = next((frame for frame in up_source if frame in up_target), None)
        if common is None:
            return None
        steps = []
        # target → common: walk up from target (applied inverted), then common → source (applied as is)
        for frame in up_target[: up_target.index(common)]:
            steps.append((frame, self._edges[frame].parent, False))
        down = [(frame, self._edges[frame].parent, True) for frame in up_source[: up_source.index(common)]]
        return TfChain(target, source, tuple(steps + list(reversed(down))))

    def is_static(self, chain: TfChain) -> bool:
        return all(self._edges[child].static for child, _, _ in chain.steps)

    def dynamic_stamps(self, chain: TfChain) -> np.ndarray:
        """(M,) sorted stamps in ns of the chain's dynamic edges, within the span all of them cover."""
        dynamic = [self._edges[child].arrays()[0] for child, _, _ in chain.steps if not self._edges[child].static]
        if not dynamic:
            return np.zeros(0, np.int64)
        lo, hi = max(s[0] for s in dynamic), min(s[-1] for s in dynamic)
        stamps = np.unique(np.concatenate(dynamic))
        return stamps[(stamps >= lo) & (stamps <= hi)]

    def transforms(self, chain: TfChain, t_ns: np.ndarray, *, nearest: bool = False) -> np.ndarray:
        """(N, 4, 4) T_target_source at (N,) times; rows are NaN where a dynamic edge has no sample around the time
        (unless `nearest`, which takes each dynamic edge's sample nearest in time)."""
        t_ns = np.atleast_1d(np.asarray(t_ns, dtype=np.int64))
        T = np.broadcast_to(np.eye(4), (len(t_ns), 4, 4)).copy()
        for child, _, up in chain.steps:
            T_parent_child = self._edges[child].at(t_ns, nearest=nearest)
            T = T @ (T_parent_child if up else invert(T_parent_child))
        return T

    def _ancestors(self, frame: str) -> list[str]:
        """`frame`, its parent, its grandparent, ... up to the root; InputError when the walk comes back to a frame
        (a cycle: no transform between two of its frames is defined)."""
        out = [frame]
        while out[-1] in self._edges:
            parent = self._edges[out[-1]].parent
            if parent in out:
                cycle = [*out[out.index(parent) :], parent]
                raise InputError(
                    f"tf: the frames {' → '.join(cycle)} form a cycle (each a child of the next); a tf tree has "
                    "none: give --camera-mount x,y,z,roll,pitch,yaw"
                )
            out.append(parent)
        return out


def describe_chain(chain: TfChain) -> str:
    """ "base_link → camera_link → camera_color_optical_frame"."""
    return " → ".join(chain.frames())
