"""Placing bubbles without overlap (random sequential placement, relaxation) and their smooth shape perturbations."""

from __future__ import annotations

import numpy as np

from bubsub.core.foam.checks import count

__all__ = ['fourier_perturbation', 'smooth_sphere_perturbation', 'place', 'relax']


def fourier_perturbation(rng, t, kmax, amp):
    """Random zero-mean outline perturbation with modes 2..kmax, max |.| in [amp/2, amp]."""
    if amp == 0:
        return np.zeros_like(t)
    k = np.arange(2, kmax + 1)
    coef = rng.normal(size=k.size) / k  # smoother: high modes weaker
    phase = rng.uniform(0, 2 * np.pi, k.size)
    f = (coef[:, None] * np.cos(k[:, None] * t[None, :] + phase[:, None])).sum(axis=0)
    peak = np.abs(f).max()
    scale = rng.uniform(0.5, 1.0) * amp
    return f * (scale / peak) if peak > 0 else f


def smooth_sphere_perturbation(rng, u, wavenumber, amp, n_waves=6):
    """Random smooth function on unit vectors ``u`` (m, 3), zero-mean-ish, max |.| in [amp/2, amp]."""
    k = rng.normal(size=(n_waves, 3))
    k *= wavenumber / np.linalg.norm(k, axis=1, keepdims=True)
    phase = rng.uniform(0, 2 * np.pi, n_waves)
    weight = rng.normal(size=n_waves)
    f = (weight[:, None] * np.cos(k @ u.T + phase[:, None])).sum(axis=0)
    f -= f.mean()
    peak = np.abs(f).max()
    scale = rng.uniform(0.5, 1.0) * amp
    return f * (scale / peak) if peak > 0 else f


def place(rng, bound, half, gap, max_attempts, what, size, packing="random"):
    """Disjoint centres for disks/balls of radius ``bound`` in the box ``|x_i| <= half_i``.

    ``packing="random"``: random sequential addition, largest first; each
    bubble takes the first free one of up to ``max_attempts`` uniformly
    random centres or, if none is free, a random free node of a fine
    lattice over the allowed region. ``packing="dense"``: all centres start
    uniformly random and overlapping pairs are pushed apart (and pulled back
    inside the walls) until none overlaps (collective rearrangement); this
    reaches gas fractions of about 0.5-0.6.
    """
    if packing not in ("random", "dense"):
        raise ValueError(f"packing must be 'random' or 'dense', got {packing!r}")
    d = len(half)
    n = len(bound)
    attempts = count("max_attempts", max_attempts)
    room = half[None, :] - bound[:, None]  # (n, d) allowed |centre| per bubble
    if np.any(room < 0):
        b = int(np.argmax(np.any(room < 0, axis=1)))
        raise ValueError(
            f"a bubble of radius {bound[b]:.3g} mm does not fit in the {what} of size {size} "
            f"with the margin; reduce radius_range or margin"
        )
    if packing == "dense":
        return relax(rng, bound, room, gap, attempts, n, what)
    centres = np.empty((n, d))

    def free(cand, b):
        if b == 0:
            return np.ones(len(cand), dtype=bool)
        ok = np.ones(len(cand), dtype=bool)
        for start in range(0, len(cand), 4096):
            c = cand[start: start + 4096]
            dist = np.linalg.norm(c[:, None, :] - centres[None, :b, :], axis=2)
            ok[start: start + 4096] = np.all(dist >= bound[None, :b] + bound[b] + gap, axis=1)
        return ok

    for b in range(n):
        best = None
        done = 0
        while done < attempts and best is None:
            m = min(256, attempts - done)
            cand = rng.uniform(-room[b], room[b], size=(m, d))
            done += m
            ok = free(cand, b)
            if ok.any():
                best = cand[np.argmax(ok)]
        if best is None:
            # lattice of about 200k nodes over the allowed region, randomly shifted
            step = max(float(np.prod(2 * room[b] + 1e-12) / 2e5) ** (1.0 / d), 1e-3 * float(bound[b]))
            axes = [np.arange(-r, r + 1e-12, step) + rng.uniform(0, step) for r in room[b]]
            axes = [a[a <= r] if a.size > 1 else np.zeros(1) for a, r in zip(axes, room[b])]
            grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, d)
            idx = np.nonzero(free(grid, b))[0]
            if idx.size:
                best = grid[idx[rng.integers(idx.size)]]
        if best is None:
            raise ValueError(
                f"could not place bubble {b + 1} of {n} (radius {bound[b]:.3g} mm) without overlap; "
                f"ask for fewer bubbles, smaller radii or a smaller gap, or use packing='dense'"
            )
        centres[b] = best
    return centres


def relax(rng, bound, room, gap, iterations, n, what):
    """Collective rearrangement: push overlapping pairs apart until all are disjoint."""
    d = room.shape[1]
    x = rng.uniform(-room, room)
    need = bound[:, None] + bound[None, :] + gap  # required centre distances
    np.fill_diagonal(need, 0.0)
    aim = need * 1.002 + 1e-9  # push a little further, so jammed clusters settle in finite time
    mass = bound**d
    w = mass[None, :] / (mass[:, None] + mass[None, :])  # share of a push taken by i
    for _ in range(iterations):
        diff = x[:, None, :] - x[None, :, :]
        dist = np.linalg.norm(diff, axis=2)
        np.fill_diagonal(dist, np.inf)
        if np.all(dist >= need):
            return x
        overlap = aim - dist
        hit = overlap > 0
        direction = diff / np.where(np.isfinite(dist) & (dist > 0), dist, 1.0)[..., None]
        same = hit & (dist == 0)
        if same.any():  # coincident centres: push apart along a random direction
            direction[same] = rng.normal(size=(int(same.sum()), d))
        push = np.where(hit, overlap * w, 0.0)
        x += (push[..., None] * direction).sum(axis=1)
        np.clip(x, -room, room, out=x)
    raise ValueError(
        f"could not pack {n} bubbles without overlap in the {what} after {iterations} relaxation "
        f"steps; ask for fewer bubbles, smaller radii or a smaller gap"
    )
