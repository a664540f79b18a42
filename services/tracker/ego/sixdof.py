"""6-DoF camera pose from events by aligning a semi-dense 3D map to them (seed 001: EVO's image-to-model
alignment, ESVO's registration of map points on a distance field of the latest events).

Every `step_us` the latest `window_events` events are drawn as a binary edge image; its distance
transform (truncated) is a field that is zero on the edges the camera sees now. The map's points in view
from the predicted pose (constant velocity, over the last `velocity_updates`) are projected into it, and
the pose is moved by Gauss-Newton on the 6 parameters of a small motion so that the sum of their squared
distances, Huber-weighted (points with no edge near them, occluded or unseen by events, count less), plus a
prior on the step from the prediction, is least: first on a half-resolution field, whose basin is twice as
wide, then at full resolution. Whether the alignment holds is told by the share of points within
`inlier_px` of an edge beyond what chance gives, and by the step it took: a lost update reports no pose,
and the next ones start from the last good pose, without its velocity, until one holds again (at a
higher share than tracking needs to go on).

Where the camera has an IMU, its gyro predicts the rotation instead, and holds it tighter (see `gyro.py`).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from services.mapper.trajectory import Trajectory
from services.tracker.ego.gyro import Gyro
from services.tracker.ego.rotation import LOST, TRACKING  # an estimate's states, as the rotation tracker's


GYRO_KEPT_US = 10_000_000  # gyro samples kept while lost, behind the latest update (a live loss may last long)


@dataclass
class SixDofParams:
    step_us: int = 20_000  # an estimate this often (50 Hz)
    window_events: int = 6_000  # the latest events drawn as the edge image (6 ms at 1 Mev/s; 10 000 drifted more)
    map_keyframes: int = 6  # the map aligned to: the latest keyframes' points
    max_points: int = 3_000  # map points aligned per update at most (a random sample of those in view)
    truncate_px: float = 8.0  # the distance field's ceiling: points farther from any edge pull no harder
    huber_px: float = 1.5  # residuals above this weigh as 1 / residual (occluded or unseen map points)
    scales: tuple[int, ...] = (2, 1)  # coarse to fine: the field at 1/2 resolution, then full
    iterations: int = 6  # Gauss-Newton steps per scale
    inlier_px: float = 1.5  # a point within this of an edge is explained by the events
    # the share of points explained beyond what a random placement gets (the share of the image that near an
    # edge), as a share of what it could be: 0.2-0.8 tracking on the dev sequences, 0.02 at most 3 deg and 10 cm
    # off, and under 0 on uniform noise; under this the update is lost (at 0.12, dev seed 5 was lost for its
    # last 3.5 s where its map left the view, still within 8 cm: 3.1 % ATE, 1.5 % at 0.06)
    min_inliers: float = 0.06
    # ... and a lost one is found again only at this share: aligned to uniform noise from anywhere, with no jump
    # limit, an update once reached 0.07
    recover_inliers: float = 0.12
    min_points: int = 200  # fewer map points in view than this: nothing to align to (lost)
    # an alignment that moves the pose further than this from the prediction (m, deg) in one update is lost: the
    # camera does not jump, a wrong minimum does
    max_jump_m: float = 0.05
    max_jump_deg: float = 3.0
    # the prediction's velocity is the mean over this many updates (over 1 update, noise along the direction
    # the events leave free, a sideways move against a turn, fed back and ran away; 5 and 10: 3.4 and 3.0 % ATE)
    velocity_updates: int = 10
    # the prediction as a prior: a step off it by this much (m, rad) costs as much as one point one pixel off
    # (off: 5.3 % ATE; 2 mm, 0.001 rad: 5.8 %)
    prior_m: float = 0.005
    prior_rad: float = 0.002
    # ... the rotation's, where a gyro predicts it (`gyro.py`): over an update it is off by a hundredth of a degree,
    # so the events tell the translation. Dev seeds 1-6 and 21-26 with the simulated gyro, ATE within 2 % on how
    # many of 12 (mean %), one camera / stereo: 0.002: 2 of 6 (12.2) on seeds 1-6 alone; 0.0006: 3 of 6 (4.0) on
    # 1-6; 0.0003: 7 (2.28) / 11 (1.14); 0.0002: 10 (2.67, seed 26 at 18) / 11 (1.23); 0.00015: 10 (2.02) / 10 (1.41)
    prior_rad_gyro: float = 0.0002
    # lost with a gyro, the prediction's centre goes on at the last good velocity for up to this long, its turn
    # the gyro's: the loss is most often the map leaving the view, not the pose going wrong (one camera, dev seed
    # 23: lost 3.9 cm off, then 188 of 500 updates lost, 32 with this; dev seeds' mean ATE 2.67 -> 1.70 %; stereo
    # unchanged). Without a gyro it starts from the last good pose (on its velocity it took worse poses sooner)
    dead_reckoning_us: int = 1_000_000


@dataclass
class PoseEstimate:
    t_us: int
    R: np.ndarray  # 3 x 3, camera to world
    p: np.ndarray  # 3, camera centre in the world (m)
    state: int
    inliers: float  # share of the aligned map points that landed on an edge, beyond chance (see `min_inliers`)
    points: int  # map points aligned
    omega: np.ndarray  # angular velocity (rad/s, camera frame) over the good poses kept; zeros when lost

    def tum_row(self) -> list[float]:
        """t tx ty tz qx qy qz qw."""
        return [self.t_us / 1e6, *self.p.tolist(), *Rotation.from_matrix(self.R).as_quat().tolist()]


def distance_field(x: np.ndarray, y: np.ndarray, width: int, height: int, scale: int,
                   truncate: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The truncated distance (px of this scale) of each pixel to the nearest pixel with an event, with its
    x and y gradients, at 1 / `scale` resolution."""
    w, h = -(-width // scale), -(-height // scale)
    edges = np.full((h, w), 255, np.uint8)
    edges[np.asarray(y, np.intp) // scale, np.asarray(x, np.intp) // scale] = 0
    field = np.minimum(cv2.distanceTransform(edges, cv2.DIST_L2, cv2.DIST_MASK_PRECISE), truncate)
    gx = cv2.Sobel(field, cv2.CV_32F, 1, 0, ksize=1) * 0.5
    gy = cv2.Sobel(field, cv2.CV_32F, 0, 1, ksize=1) * 0.5
    return field, gx, gy


def _bilinear(images: tuple[np.ndarray, ...], u: np.ndarray, v: np.ndarray) -> list[np.ndarray]:
    """The images sampled at (u, v), which lie inside them by at least a pixel."""
    x0, y0 = np.floor(u).astype(np.intp), np.floor(v).astype(np.intp)
    fx, fy = (u - x0).astype(np.float32), (v - y0).astype(np.float32)
    out = []
    for im in images:
        a, b, c, d = im[y0, x0], im[y0, x0 + 1], im[y0 + 1, x0], im[y0 + 1, x0 + 1]
        out.append((a * (1 - fx) + b * fx) * (1 - fy) + (c * (1 - fx) + d * fx) * fy)
    return out


def _exp_se3(xi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation and translation of the small motion xi = (v, w) (first order in v, exact in w)."""
    v, w = xi[:3], xi[3:]
    R, _ = cv2.Rodrigues(w.reshape(3, 1))
    return R, v


def align(points: np.ndarray, R_cw: np.ndarray, t_cw: np.ndarray, fields: list[tuple[int, tuple]],
          K: np.ndarray, params: SixDofParams, prior_rad: float | None = None) -> tuple[np.ndarray, np.ndarray, float]:
    """T_cam_world refined so that `points` (N x 3, world) land on the events' edges, coarse to fine over
    `fields` ((scale, distance_field(...)) pairs), held to the prediction by `params.prior_m` and `prior_rad`
    (`params.prior_rad` unless given); with the share of points within `inlier_px` of an edge at the finest
    scale beyond chance (see `SixDofParams.min_inliers`)."""
    R, t = R_cw.copy(), t_cw.copy()
    share = 0.0
    off = np.zeros(6)  # the steps taken from the prediction so far (first order)
    prior = np.zeros(6)
    if params.prior_m > 0:
        prior[:] = [1 / params.prior_m ** 2] * 3 + [1 / (prior_rad or params.prior_rad) ** 2] * 3
    for scale, (field, gx, gy) in fields:
        fx, fy, cx, cy = K[0, 0] / scale, K[1, 1] / scale, (K[0, 2] + 0.5) / scale - 0.5, (K[1, 2] + 0.5) / scale - 0.5
        h, w = field.shape
        near = params.inlier_px / scale
        chance = float((field <= near).mean())  # the share a random placement would get
        for _ in range(params.iterations):
            Xc = points @ R.T + t
            z = Xc[:, 2]
            ok = z > 0.1
            u = np.where(ok, fx * Xc[:, 0] / np.where(ok, z, 1) + cx, -10)
            v = np.where(ok, fy * Xc[:, 1] / np.where(ok, z, 1) + cy, -10)
            ok &= (u >= 0) & (u < w - 1) & (v >= 0) & (v < h - 1)
            if ok.sum() < params.min_points:
                return R, t, 0.0
            X, u, v = Xc[ok], u[ok], v[ok]
            r, du, dv = _bilinear((field, gx, gy), u, v)
            share = (float((r <= near).mean()) - chance) / max(1.0 - chance, 1e-6)
            iz = 1.0 / X[:, 2]
            # d(u, v) / d(X_cam), then d(X_cam) / d(xi) = [I | -[X]x] for xi = (v, w)
            gu, gv = du * fx * iz, dv * fy * iz
            gz = -(gu * X[:, 0] + gv * X[:, 1]) * iz
            J = np.column_stack([gu, gv, gz,
                                 gv * -X[:, 2] + gz * X[:, 1],
                                 gu * X[:, 2] - gz * X[:, 0],
                                 -gu * X[:, 1] + gv * X[:, 0]])
            k = params.huber_px / scale
            wgt = np.where(r <= k, 1.0, k / np.maximum(r, 1e-6))
            H = (J * wgt[:, None]).T @ J
            g = (J * wgt[:, None]).T @ r
            H[np.diag_indices(6)] *= 1.0 + 1e-3
            H[np.diag_indices(6)] += 1e-6 + prior / scale ** 2
            g += prior / scale ** 2 * off
            try:
                xi = -np.linalg.solve(H, g)
            except np.linalg.LinAlgError:
                break
            off += xi
            dR, dt = _exp_se3(xi)
            R, t = dR @ R, dR @ t + dt
            if np.abs(xi).max() < 1e-5:
                break
    return R, t, share


class SixDofTracker:
    """Events (undistorted, sorted) in, poses out: each `step_us` the map (`add_points`) is aligned to the
    latest events, from the pose predicted by the last good ones (`start` gives the first), its rotation by
    the `gyro` where one is given and covers the update."""

    def __init__(self, K: np.ndarray, width: int, height: int, params: SixDofParams | None = None,
                 seed: int = 0, gyro: Gyro | None = None) -> None:
        self.K, self.width, self.height = np.asarray(K, np.float64), width, height
        self.params = params or SixDofParams()
        self.gyro = gyro
        self._maps: list[np.ndarray] = []
        self._points = np.zeros((0, 3))  # the maps' points in one array
        self._rng = np.random.default_rng(seed)
        self._tail = np.zeros(0, [("x", np.uint16), ("y", np.uint16), ("t", np.int64)])
        self._poses: list[tuple[int, np.ndarray, np.ndarray]] = []  # (t_us, R_cw, t_cw) of the last good ones
        self.next_us: int | None = None
        self.state = LOST

    def start(self, t_us: int, R_wc: np.ndarray, p: np.ndarray, earlier: tuple[int, np.ndarray, np.ndarray]
              | None = None) -> None:
        """A known pose (camera to world) at `t_us`, and optionally one before it for the first velocity."""
        self._poses = [(int(ti), Ri.T.copy(), -Ri.T @ pi) for ti, Ri, pi in ([earlier] if earlier else []) +
                       [(t_us, R_wc, p)]]
        self.next_us = t_us + self.params.step_us
        self.state = TRACKING

    def start_on(self, known: Trajectory, t_us: int) -> None:
        """At `t_us` of a known motion, with its pose `step_us` before for the first velocity."""
        step = self.params.step_us
        (R1,), (p1,) = known.at(t_us)
        (R0,), (p0,) = known.at(t_us - step)
        self.start(t_us, R1, p1, (t_us - step, R0, p0))

    def add_points(self, points: np.ndarray) -> None:
        """World points of one more keyframe of the map; only the latest `map_keyframes` are kept."""
        points = np.asarray(points, np.float64).reshape(-1, 3)
        if len(points):
            self._maps = [*self._maps, points][-self.params.map_keyframes:]
            self._points = np.concatenate(self._maps)

    @property
    def map_points(self) -> int:
        return len(self._points)

    def add(self, events: np.ndarray) -> list[PoseEstimate]:
        """Events sorted by time; the estimates of the update times they passed."""
        out: list[PoseEstimate] = []
        if self.next_us is None or not len(events):
            return out
        keep = max(self.params.window_events, 1)
        while len(events) and int(events["t"][-1]) >= self.next_us:
            cut = int(np.searchsorted(events["t"], self.next_us, side="left"))
            self._remember(events[:cut], keep)
            events = events[cut:]
            out.append(self._update(self.next_us))
            self.next_us += self.params.step_us
        self._remember(events, keep)
        return out

    def _remember(self, events: np.ndarray, keep: int) -> None:
        if len(events):
            part = np.empty(len(events), self._tail.dtype)
            for f in ("x", "y", "t"):
                part[f] = events[f]
            self._tail = np.concatenate([self._tail, part])[-keep:]

    def _predict(self, t_us: int) -> tuple[np.ndarray, np.ndarray, bool]:
        """T_cam_world at `t_us` by constant velocity between the oldest and the latest of the good poses kept
        (the latest alone if it is the only one, or while lost), turned as the gyro says where it tells (and
        whether it did); lost, with the gyro, the centre goes on at the velocity of the good poses kept for up
        to `dead_reckoning_us`."""
        t1, R1, c1 = self._poses[-1]
        R, t = R1, c1
        if len(self._poses) >= 2 and self.state != LOST:
            t0, R0, c0 = self._poses[0]
            f = (t_us - t1) / max(t1 - t0, 1)
            dR = R1 @ R0.T  # T1 T0^-1, applied again for the time since t1
            rvec, _ = cv2.Rodrigues(dR)
            Rs, _ = cv2.Rodrigues(rvec * f)
            R, t = Rs @ R1, Rs @ c1 + f * (c1 - dR @ c0)
        turn = self.gyro.turn(t1, t_us) if self.gyro is not None else None
        if turn is None:
            return R, t, False
        R_gyro = turn.T @ R1
        centre = -R.T @ t
        if self.state == LOST and len(self._poses) >= 2:  # the turn known, the camera is taken on as it went
            t0, R0, c0 = self._poses[0]
            velocity = (R0.T @ c0 - R1.T @ c1) / max(t1 - t0, 1)  # camera centres -R^T t, per us
            centre = centre + velocity * min(t_us - t1, self.params.dead_reckoning_us)
        return R_gyro, -R_gyro @ centre, True  # the same camera centre (or where it went on to), turned

    def _update(self, t_us: int) -> PoseEstimate:
        p = self.params
        R0, t0, turned = self._predict(t_us)
        points = self._visible(R0, t0)
        R, t, share = R0, t0, 0.0
        if len(points) >= p.min_points and len(self._tail):
            fields = [(s, distance_field(self._tail["x"], self._tail["y"], self.width, self.height, s,
                                         p.truncate_px)) for s in p.scales]
            R, t, share = align(points, R0, t0, fields, self.K, p, p.prior_rad_gyro if turned else None)
        turn = np.degrees(np.linalg.norm(cv2.Rodrigues(R @ R0.T)[0]))
        moved = np.linalg.norm(R.T @ t - R0.T @ t0)
        # found again after a loss, the camera has moved on from the last good pose: no jump limit, no old velocity
        recovered = self.state == LOST
        enough = share >= (p.recover_inliers if recovered else p.min_inliers)
        held = enough and (recovered or (moved <= p.max_jump_m and turn <= p.max_jump_deg))
        self.state = TRACKING if held else LOST
        omega = np.zeros(3)
        if held:
            if self.gyro is not None and not recovered:  # its turn since the last good pose, seen
                t_last, R_last, _ = self._poses[-1]
                self.gyro.learn(t_last, t_us, R_last @ R.T)
            self._poses = [*([] if recovered else self._poses), (t_us, R, t)][-p.velocity_updates - 1:]
            (ta, Ra, _), (tb, Rb, _) = self._poses[0], self._poses[-1]
            if tb > ta:  # the turn from the oldest kept camera to the latest, in the camera's frame
                omega = cv2.Rodrigues(Ra @ Rb.T)[0].ravel() / ((tb - ta) / 1e6)
        if self.gyro is not None:  # predictions start from the last good pose (lost for long, too old to turn from)
            self.gyro.forget_before(max(self._poses[-1][0], t_us - GYRO_KEPT_US))
        return PoseEstimate(t_us, R.T, -R.T @ t, self.state, share, len(points), omega)

    def _visible(self, R: np.ndarray, t: np.ndarray) -> np.ndarray:
        """A random sample of up to `max_points` map points in view from T_cam_world (R, t)."""
        points = self._points
        Xc = points @ R.T + t
        z = Xc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = self.K[0, 0] * Xc[:, 0] / z + self.K[0, 2]
            v = self.K[1, 1] * Xc[:, 1] / z + self.K[1, 2]
        inside = (z > 0.1) & (u >= 1) & (u < self.width - 2) & (v >= 1) & (v < self.height - 2)
        idx = np.flatnonzero(inside)
        if len(idx) > self.params.max_points:
            idx = self._rng.choice(idx, self.params.max_points, replace=False)
        return points[idx]
