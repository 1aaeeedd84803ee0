"""Which image pairs to match: all of them for small sets, retrieved neighbours for large ones.

Matching every pair costs N(N−1)/2 descriptor matchings and dominates SfM time on a
CPU (70 of 87 s for 119 photos of 400²). Most of those pairs see nothing in common.
For larger sets each image is matched with the images most similar to it under a
bag of visual words built on the fly from the capture's own SIFT descriptors (a
small k-means vocabulary, tf-idf weighted histograms, cosine similarity) plus its
neighbours in file-name order (photos and video frames are usually named in capture
order). No vocabulary file is downloaded, so it works offline and on any capture.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

# Measured in docs/benchmarks.md ("Structure from motion"): below this many images
# exhaustive matching costs little more than retrieval and cannot miss a pair.
EXHAUSTIVE_MAX_IMAGES = 40
RETRIEVAL_NEIGHBOURS = 20  # most similar images matched with each image
SEQUENTIAL_NEIGHBOURS = 3  # images before/after in name order matched with each image
VOCAB_WORDS = 512
VOCAB_SAMPLE = 60_000  # descriptors the vocabulary is fitted on
VOCAB_ITERATIONS = 8


def exhaustive_pairs(n: int) -> list[tuple[int, int]]:
    """Every unordered pair (i < j) of ``n`` images."""
    return [(i, j) for i in range(n) for j in range(i + 1, n)]


def sequential_pairs(n: int, window: int) -> set[tuple[int, int]]:
    """Each image with the ``window`` images after it in order (i < j)."""
    return {(i, j) for i in range(n) for j in range(i + 1, min(n, i + 1 + window))}


def _normalise(x: np.ndarray) -> np.ndarray:
    return x / np.maximum(np.linalg.norm(x, axis=1, keepdims=True), 1e-12)


def _assign(x: np.ndarray, words: np.ndarray, chunk: int = 16384) -> np.ndarray:
    """Index of the nearest word for each row of ``x`` (unit vectors: max dot product)."""
    out = np.empty(len(x), dtype=np.int64)
    for s in range(0, len(x), chunk):
        out[s : s + chunk] = np.argmax(x[s : s + chunk] @ words.T, axis=1)
    return out


def fit_vocabulary(
    descriptors: Sequence[np.ndarray],
    words: int = VOCAB_WORDS,
    sample: int = VOCAB_SAMPLE,
    iterations: int = VOCAB_ITERATIONS,
    seed: int = 0,
) -> np.ndarray:
    """Spherical k-means words (K, D), unit length, from an even sample of all images."""
    rng = np.random.default_rng(seed)
    per_image = max(1, sample // max(1, len(descriptors)))
    parts = [
        d[rng.choice(len(d), min(len(d), per_image), replace=False)] for d in descriptors if len(d)
    ]
    if not parts:
        raise ValueError("no descriptors to build a vocabulary from")
    x = _normalise(np.concatenate(parts).astype(np.float32))
    k = min(words, len(x))
    centres = x[rng.choice(len(x), k, replace=False)].copy()
    for _ in range(iterations):
        label = _assign(x, centres)
        sums = np.zeros_like(centres)
        np.add.at(sums, label, x)
        empty = np.bincount(label, minlength=k) == 0
        sums[empty] = x[rng.choice(len(x), int(empty.sum()))]  # re-seed unused words
        centres = _normalise(sums)
    return centres


def similarity(descriptors: Sequence[np.ndarray], vocabulary: np.ndarray) -> np.ndarray:
    """(N, N) cosine similarity of tf-idf visual-word histograms; the diagonal is −inf."""
    n, k = len(descriptors), len(vocabulary)
    hist = np.zeros((n, k), dtype=np.float64)
    for i, d in enumerate(descriptors):
        if len(d):
            words = _assign(_normalise(d.astype(np.float32)), vocabulary)
            hist[i] = np.bincount(words, minlength=k)
    df = (hist > 0).sum(0)
    idf = np.log((n + 1) / (df + 1))
    v = _normalise(hist / np.maximum(hist.sum(1, keepdims=True), 1) * idf)
    s = v @ v.T
    np.fill_diagonal(s, -np.inf)
    return s


def retrieval_pairs(
    sim: np.ndarray,
    neighbours: int = RETRIEVAL_NEIGHBOURS,
    window: int = SEQUENTIAL_NEIGHBOURS,
) -> list[tuple[int, int]]:
    """Pairs (i < j): each image's ``neighbours`` most similar images plus its order window."""
    n = len(sim)
    pairs = sequential_pairs(n, window)
    k = min(neighbours, n - 1)
    top = np.argsort(-sim, axis=1)[:, :k]
    for i in range(n):
        for j in top[i]:
            pairs.add((min(i, int(j)), max(i, int(j))))
    return sorted(pairs)


def pairs_with(
    images: Sequence[int],
    n: int,
    done: set[tuple[int, int]],
    *,
    sim: np.ndarray | None = None,
    budget: int | None = None,
) -> list[tuple[int, int]]:
    """Not-yet-matched pairs between ``images`` and the other images (i < j).

    All of them, unless that exceeds ``budget`` pairs: then each image is paired with
    its most similar images under ``sim`` (an even share of the budget each), so a
    second chance for many images costs at most ``budget`` matchings.
    """
    per = n - 1
    if budget is not None and sim is not None and images:
        per = max(1, min(n - 1, budget // len(images)))
    out = set()
    for i in images:
        order = np.argsort(-sim[i]) if sim is not None else np.arange(n)
        picked = 0
        for j in order:
            j = int(j)
            if j == i:
                continue
            p = (min(i, j), max(i, j))
            if p not in done and p not in out:
                out.add(p)
                picked += 1
                if picked >= per:
                    break
    return sorted(out)
