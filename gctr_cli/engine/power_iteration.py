"""Stage 4: tensor power iteration (Algorithm 1, lines 5-10) to a soft assignment matrix.

One step: ``x <- H3 (x) x (x) x + w * H1`` where the third-order product is computed for the
supersymmetric tensor with three ``np.bincount`` calls; each term is L2-normalised before they are
added so that ``w`` is a true relative weight. The result is then made approximately doubly
stochastic by alternating row and column L2 normalisations (as the authors' reference code does)
and normalised to unit length.
"""

from __future__ import annotations

import numpy as np

from gctr_cli.engine.tensor import SparseTensor3, SparseVector


def _normalise_rows_cols(x: np.ndarray, n1: int, n2: int, rounds: int) -> np.ndarray:
    m = x.reshape(n1, n2)
    for _ in range(rounds):
        m = m / np.maximum(np.sqrt(np.einsum("ij,ij->i", m, m)), 1e-300)[:, None]
        m = m / np.maximum(np.sqrt(np.einsum("ij,ij->j", m, m)), 1e-300)[None, :]
    return m.ravel()


def tensor_product(tensor: SparseTensor3, x: np.ndarray, slots: np.ndarray | None = None) -> np.ndarray:
    """``H3 (x) x (x) x`` for a supersymmetric sparse tensor: each entry feeds all three slots.

    ``slots`` is ``concatenate([a, b, c])`` (pass it when calling repeatedly: one ``np.bincount``
    over all three slots instead of three)."""
    xa, xb, xc = x[tensor.a], x[tensor.b], x[tensor.c]
    v = tensor.values
    if slots is None:
        slots = np.concatenate([tensor.a, tensor.b, tensor.c])
    return np.bincount(slots, weights=np.concatenate([v * xb * xc, v * xa * xc, v * xa * xb]), minlength=tensor.size)


def power_iteration(tensor: SparseTensor3, first_order: SparseVector | None = None,
                    first_order_weight: float = 1.0, iterations: int = 40, tol: float = 1e-6,
                    normalisation_rounds: int = 5, start: np.ndarray | None = None) -> tuple[np.ndarray, int]:
    """Return the soft assignment matrix X (n1, n2) and the number of iterations run.

    ``start`` warm-starts from a previous assignment (the outer loop passes its last X); the
    default is the uniform assignment ``1 / n2``.
    """
    n1, n2 = tensor.n1, tensor.n2
    n = n1 * n2
    x = np.full(n, 1.0 / n2) if start is None else np.asarray(start, dtype=float).ravel().copy()
    h1 = np.zeros(n)
    if first_order is not None and len(first_order.index) and first_order_weight > 0:
        np.add.at(h1, first_order.index, first_order.values)
        h1 *= first_order_weight / np.linalg.norm(h1)
    slots = np.concatenate([tensor.a, tensor.b, tensor.c])
    it = 0
    for it in range(1, iterations + 1):  # noqa: B007 (the count is returned)
        h3 = tensor_product(tensor, x, slots) if len(tensor.values) else np.zeros(n)
        norm3 = np.linalg.norm(h3)
        x_new = (h3 / norm3 if norm3 > 0 else h3) + h1
        x_new = _normalise_rows_cols(x_new, n1, n2, normalisation_rounds)
        norm = np.linalg.norm(x_new)
        if norm == 0:
            break
        x_new /= norm
        delta = np.linalg.norm(x_new - x)
        x = x_new
        if delta < tol:
            break
    return x.reshape(n1, n2), it
