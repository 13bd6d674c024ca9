"""Least-motion ChainMail answer by a plain Bellman-Ford loop (the oracle of the ChainMail tests).

Nothing here calls torchdeform. Per coordinate ``c``, a link ``(p, q, a)`` (elements ``p`` and
``q = p + e_a``) allows ``x_q[c] - x_p[c]`` in ``bounds(p, a, c) = (lo, hi)``. After the picked
elements move by ``delta``, every other element moves the least that satisfies all links: for a
pull, ``x_n = max(x_n, max over links of x_q + (bound on x_n - x_q))``, relaxed until nothing
changes (Bellman-Ford on the constraint graph), and the mirror image for a push.
"""

from __future__ import annotations

import math


def least_motion(x, shape, links, bounds, picks, delta):
    """Positions ``(3, D, H, W)`` (numpy) after moving ``picks`` by ``delta`` (3,).

    Args:
        x: positions or offsets ``(3, D, H, W)`` before the move.
        shape: ``(D, H, W)``.
        links: ``[(p, q, a), ...]`` element index triples and the axis joining them.
        bounds: ``bounds(p, a, c) -> (lo, hi)``: allowed ``x_q[c] - x_p[c]``.
        picks: the moved elements; delta: their displacement.
    """
    new = x.copy()
    nodes = [(i, j, k) for i in range(shape[0]) for j in range(shape[1]) for k in range(shape[2])]
    for c in range(3):
        if delta[c] == 0:
            continue
        pull = delta[c] > 0
        adj = {n: [] for n in nodes}
        for p, q, a in links:
            lo, hi = bounds(p, a, c)
            adj[q].append((p, lo, hi))  # x_q - x_p in [lo, hi]
            adj[p].append((q, -hi, -lo))  # x_p - x_q in [-hi, -lo]
        env = dict.fromkeys(nodes, -math.inf if pull else math.inf)
        for p in picks:
            env[p] = x[c][p] + delta[c]
        changed = True
        while changed:
            changed = False
            for n in nodes:
                if n in picks:
                    continue
                for q, lo, hi in adj[n]:  # x_n - x_q in [lo, hi]
                    cand = env[q] + lo if pull else env[q] + hi
                    if (pull and cand > env[n]) or (not pull and cand < env[n]):
                        env[n], changed = cand, True
        for n in nodes:
            new[c][n] = env[n] if n in picks else (max(x[c][n], env[n]) if pull else min(x[c][n], env[n]))
    return new
