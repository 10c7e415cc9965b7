"""The classical hand-eye methods, on one common form of both mountings.

Every view ties the two unknowns as Y = C_i X A_i, with A_i the target in the camera and C_i
the flange in the base (eye-in-hand: X camera in flange, Y target in base) or the base in the
flange (eye-to-hand: X camera in base, Y target in flange).

The AX = XB methods take the motion between two views, M X = X N with M = C_j^-1 C_i and
N = A_j A_i^-1 (every pair of views), and solve the rotation by Tsai-Lenz (modified
Rodrigues vectors), Park-Martin (log map, orthogonal Procrustes), Horaud-Dornaika (unit
quaternions), Andreff (Kronecker null space) or Daniilidis (dual quaternions, rotation and
translation at once); the translation (except Daniilidis) by least squares on
(R_M - I) t_X = R_X t_N - t_M; Y is then the mean of C_i X A_i. The AX = ZB methods take the
views themselves, C_i X = Y A_i^-1, and solve X and Y together: Shah (Kronecker product,
rotations first) and Li (rotations and translations in one linear system).

These are the methods of OpenCV's calibrateHandEye / calibrateRobotWorldHandEye, which the
OpenCV 5 Python build this project pins does not include; they are the start values of the
joint refinement and the benchmark's reference.
"""

from __future__ import annotations

from itertools import combinations
from typing import Literal

import numpy as np
from scipy.spatial.transform import Rotation

from calibration.handeye.rigid import Rigid, mean_rigid

Mount = Literal["eye-in-hand", "eye-to-hand"]

AX_XB_METHODS = ("tsai", "park", "horaud", "andreff", "daniilidis")
AX_ZB_METHODS = ("shah", "li")
METHODS = (*AX_XB_METHODS, *AX_ZB_METHODS)


def chain(mount: Mount, flange: Rigid) -> Rigid:
    """C_i of a view from the robot's flange pose (flange in base)."""
    return flange if mount == "eye-in-hand" else flange.inverse()


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])


def _nearest_rotation(m: np.ndarray) -> np.ndarray:
    """The rotation closest to `m` (Frobenius), any scale and sign of `m` removed."""
    if np.linalg.det(m) < 0:
        m = -m
    u, _, vt = np.linalg.svd(m)
    return u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt


def _quat(r: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z) of a rotation matrix."""
    x, y, z, w = Rotation.from_matrix(r).as_quat()
    return np.array([w, x, y, z]) * (1.0 if w >= 0 else -1.0)


def _qmul_left(q: np.ndarray) -> np.ndarray:
    """L(q) with q * p = L(q) p."""
    w, x, y, z = q
    return np.array([[w, -x, -y, -z], [x, w, -z, y], [y, z, w, -x], [z, -y, x, w]])


def _qmul_right(q: np.ndarray) -> np.ndarray:
    """R(q) with p * q = R(q) p."""
    w, x, y, z = q
    return np.array([[w, -x, -y, -z], [x, w, z, -y], [y, -z, w, x], [z, y, -x, w]])


def _from_quat(q: np.ndarray) -> np.ndarray:
    return Rotation.from_quat([q[1], q[2], q[3], q[0]]).as_matrix()


def _rotation_tsai(ms: list[Rigid], ns: list[Rigid]) -> np.ndarray:
    rows, rhs = [], []
    for m, n in zip(ms, ns, strict=True):
        pm = 2 * np.sin(_angle(m) / 2) * _axis(m)
        pn = 2 * np.sin(_angle(n) / 2) * _axis(n)
        rows.append(_skew(pm + pn))
        rhs.append(pn - pm)
    p_prime = np.linalg.lstsq(np.vstack(rows), np.concatenate(rhs), rcond=None)[0]
    p = 2 * p_prime / np.sqrt(1 + p_prime @ p_prime)
    pp = p @ p
    return ((1 - pp / 2) * np.eye(3)
            + 0.5 * (np.outer(p, p) + np.sqrt(4 - pp) * _skew(p)))


def _angle(t: Rigid) -> float:
    return float(np.linalg.norm(Rotation.from_matrix(t.rotation).as_rotvec()))


def _axis(t: Rigid) -> np.ndarray:
    v = Rotation.from_matrix(t.rotation).as_rotvec()
    return v / max(np.linalg.norm(v), 1e-300)


def _rotation_park(ms: list[Rigid], ns: list[Rigid]) -> np.ndarray:
    """R_X minimizing sum |log(R_M) - R_X log(R_N)|^2 (orthogonal Procrustes)."""
    k = sum(np.outer(Rotation.from_matrix(m.rotation).as_rotvec(),
                     Rotation.from_matrix(n.rotation).as_rotvec())
            for m, n in zip(ms, ns, strict=True))
    return _nearest_rotation(np.asarray(k))


def _rotation_horaud(ms: list[Rigid], ns: list[Rigid]) -> np.ndarray:
    """q_M * q_X = q_X * q_N: the unit quaternion that least violates all of them."""
    a = sum((lambda d: d.T @ d)(_qmul_left(_quat(m.rotation)) - _qmul_right(_quat(n.rotation)))
            for m, n in zip(ms, ns, strict=True))
    return _from_quat(np.linalg.eigh(np.asarray(a))[1][:, 0])


def _rotation_andreff(ms: list[Rigid], ns: list[Rigid]) -> np.ndarray:
    """(I - R_M kron R_N) vec(R_X) = 0 (row-major vec): the null vector, made a rotation."""
    a = np.vstack([np.eye(9) - np.kron(m.rotation, n.rotation)
                   for m, n in zip(ms, ns, strict=True)])
    return _nearest_rotation(np.linalg.svd(a)[2][-1].reshape(3, 3))


def _translation(ms: list[Rigid], ns: list[Rigid], rot: np.ndarray) -> np.ndarray:
    a = np.vstack([m.rotation - np.eye(3) for m in ms])
    b = np.concatenate([rot @ n.translation - m.translation for m, n in zip(ms, ns, strict=True)])
    return np.linalg.lstsq(a, b, rcond=None)[0]


def _dual_quat(t: Rigid) -> tuple[np.ndarray, np.ndarray]:
    q = _quat(t.rotation)
    if q[0] < 0:
        q = -q
    return q, 0.5 * _qmul_left(np.concatenate([[0.0], t.translation])) @ q


def _daniilidis(ms: list[Rigid], ns: list[Rigid]) -> Rigid:
    """Dual quaternions: the 6x8 screw constraints of every motion, the 2-D null space,
    the unit-norm combination of its two vectors (Daniilidis 1999)."""
    rows = []
    for m, n in zip(ms, ns, strict=True):
        (qa, qa_), (qb, qb_) = _dual_quat(m), _dual_quat(n)
        a, a_, b, b_ = qa[1:], qa_[1:], qb[1:], qb_[1:]
        top = np.hstack([(a - b)[:, None], _skew(a + b), np.zeros((3, 4))])
        bottom = np.hstack([(a_ - b_)[:, None], _skew(a_ + b_), (a - b)[:, None], _skew(a + b)])
        rows.append(np.vstack([top, bottom]))
    v = np.linalg.svd(np.vstack(rows))[2]
    v1, v2 = v[-2], v[-1]
    u1, w1, u2, w2 = v1[:4], v1[4:], v2[:4], v2[4:]
    # lambda1 v1 + lambda2 v2 with |q| = 1 and q . q' = 0 (s = lambda1 / lambda2)
    coeffs = [u1 @ w1, u1 @ w2 + u2 @ w1, u2 @ w2]
    roots = np.roots(coeffs).real
    best = max(roots, key=lambda s: s * s * (u1 @ u1) + 2 * s * (u1 @ u2) + u2 @ u2)
    norm2 = best * best * (u1 @ u1) + 2 * best * (u1 @ u2) + u2 @ u2
    lam2 = 1.0 / np.sqrt(norm2)
    lam1 = best * lam2
    q = lam1 * u1 + lam2 * u2
    q_ = lam1 * w1 + lam2 * w2
    t = 2 * _qmul_left(q_) @ np.array([q[0], -q[1], -q[2], -q[3]])
    return Rigid(_from_quat(q), t[1:])


def _motions(chains: list[Rigid], target: list[Rigid]) -> tuple[list[Rigid], list[Rigid]]:
    """M X = X N of every pair of views (M = C_j^-1 C_i, N = A_j A_i^-1)."""
    ms, ns = [], []
    for i, j in combinations(range(len(chains)), 2):
        ms.append(chains[j].inverse() @ chains[i])
        ns.append(target[j] @ target[i].inverse())
    return ms, ns


def _shah(a: list[Rigid], b: list[Rigid]) -> tuple[Rigid, Rigid]:
    """A_i X = Z B_i: vec(R_Z) is K vec(R_X) for K = mean(R_A kron R_B) (row-major vec),
    so both are the top singular pair of K; then the translations by least squares."""
    k = sum(np.kron(ai.rotation, bi.rotation) for ai, bi in zip(a, b, strict=True)) / len(a)
    u, _, vt = np.linalg.svd(np.asarray(k))
    rx = _nearest_rotation(vt[0].reshape(3, 3))
    rz = _nearest_rotation(u[:, 0].reshape(3, 3))
    return _translations_zb(a, b, rx, rz)


def _translations_zb(a: list[Rigid], b: list[Rigid], rx: np.ndarray,
                     rz: np.ndarray) -> tuple[Rigid, Rigid]:
    """R_A t_X - t_Z = R_Z t_B - t_A for fixed rotations."""
    rows = np.vstack([np.hstack([ai.rotation, -np.eye(3)]) for ai in a])
    rhs = np.concatenate([rz @ bi.translation - ai.translation
                          for ai, bi in zip(a, b, strict=True)])
    sol = np.linalg.lstsq(rows, rhs, rcond=None)[0]
    return Rigid(rx, sol[:3]), Rigid(rz, sol[3:])


def _li(a: list[Rigid], b: list[Rigid]) -> tuple[Rigid, Rigid]:
    """A_i X = Z B_i as one linear system in vec(R_X), vec(R_Z), t_X, t_Z (row-major vec):
    R_A R_X - R_Z R_B = 0 and R_A t_X - R_Z t_B - t_Z = -t_A; rotations then made
    orthonormal and the translations solved again with them."""
    rows, rhs = [], []
    for ai, bi in zip(a, b, strict=True):
        rot_rows = np.hstack([np.kron(ai.rotation, np.eye(3)), -np.kron(np.eye(3), bi.rotation.T),
                              np.zeros((9, 6))])
        t_rows = np.hstack([np.zeros((3, 9)), -np.kron(np.eye(3), bi.translation[None, :]),
                            ai.rotation, -np.eye(3)])
        rows += [rot_rows, t_rows]
        rhs += [np.zeros(9), -ai.translation]
    sol = np.linalg.lstsq(np.vstack(rows), np.concatenate(rhs), rcond=None)[0]
    rx = _nearest_rotation(sol[:9].reshape(3, 3))
    rz = _nearest_rotation(sol[9:18].reshape(3, 3))
    return _translations_zb(a, b, rx, rz)


def classical(method: str, mount: Mount, flange: list[Rigid],
              target: list[Rigid]) -> tuple[Rigid, Rigid]:
    """(X, Y) by one classical method from the flange poses and the target-in-camera poses
    of the same views."""
    chains = [chain(mount, f) for f in flange]
    if method in AX_XB_METHODS:
        ms, ns = _motions(chains, target)
        if method == "daniilidis":
            x = _daniilidis(ms, ns)
        else:
            solve = {"tsai": _rotation_tsai, "park": _rotation_park,
                     "horaud": _rotation_horaud, "andreff": _rotation_andreff}[method]
            rot = solve(ms, ns)
            x = Rigid(rot, _translation(ms, ns, rot))
        return x, mean_rigid([c @ x @ a for c, a in zip(chains, target, strict=True)])
    if method in AX_ZB_METHODS:
        b = [t.inverse() for t in target]
        return (_shah if method == "shah" else _li)(chains, b)
    raise ValueError(f"method: expected one of {', '.join(METHODS)}, got {method!r}")
