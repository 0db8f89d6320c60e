"""Index fit and query time against map size, and recall@1 of the approximate indexes.

Random 2048-d Gaussian descriptors (the issue's test; real descriptors cluster, which
makes IVF and HNSW far easier than this). For each map size N:

- exact references: index=faiss kind=flat, and (N <= --max-exhaustive) relocfw's
  numpy index=exhaustive and the paper's index=kmeans (k=40, one k-means run);
- kind=ivf (nlist = sqrt(N)) at several nprobe, kind=hnsw (N <= --max-hnsw) at
  several ef_search: recall@1 against flat over --queries queries;
- precision=float16 and pca_dim=256 with flat: recall and memory.

Query time is per call with ONE descriptor (a query's candidates arrive in small
batches; one is the worst case per descriptor). Memory is the serialized index
size per descriptor. Prints a table, writes JSON.

    .venv/bin/python benchmarks/index_scale.py --sizes 10000 100000 1000000
"""

from __future__ import annotations

import argparse
import gc
import platform
import time
from pathlib import Path

import numpy as np
from common import write_json  # benchmarks/, the script's own folder

from relocfw.plugins.exhaustive_index import ExhaustiveIndex
from relocfw.plugins.faiss_index import FaissIndex
from relocfw.plugins.kmeans_index import KMeansIndex


def random_descriptors(count: int, dim: int, seed: int) -> np.ndarray:
    """float32 Gaussian rows, made in chunks (a 10^6 x 2048 map is 8 GB as it is)."""
    rng = np.random.default_rng(seed)
    out = np.empty((count, dim), dtype=np.float32)
    for start in range(0, count, 65536):
        stop = min(start + 65536, count)
        out[start:stop] = rng.standard_normal((stop - start, dim), dtype=np.float32)
    return out


def timed_fit(index, features: np.ndarray) -> float:
    start = time.perf_counter()
    index.fit(features)
    return time.perf_counter() - start


def query_ms(index, queries: np.ndarray, calls: int = 20) -> float:
    """Milliseconds per distance() call with one descriptor."""
    index.distance(queries[:1])  # warm-up
    start = time.perf_counter()
    for i in range(calls):
        index.distance(queries[i % len(queries)][None])
    return 1000 * (time.perf_counter() - start) / calls


def recall(index, queries: np.ndarray, truth: np.ndarray) -> float:
    return float(np.mean(index.neighbours(queries, 1)[1][:, 0] == truth))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[10_000, 100_000])
    parser.add_argument("--dim", type=int, default=2048)
    parser.add_argument("--queries", type=int, default=100)
    parser.add_argument("--max-exhaustive", type=int, default=100_000)
    parser.add_argument("--max-hnsw", type=int, default=100_000)
    parser.add_argument("--nprobe", type=int, nargs="+", default=[8, 32, 128])
    parser.add_argument("--ef-search", type=int, nargs="+", default=[32, 128, 512])
    parser.add_argument("--pca-dim", type=int, default=256)
    parser.add_argument(
        "--only",
        nargs="+",
        default=["exact", "ivf", "hnsw", "float16", "pca"],
        help="which rows besides faiss flat (always: it is the recall reference)",
    )
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/index_scale.json"))
    args = parser.parse_args()
    rows = []

    def record(size: int, name: str, fit_s: float, index, ms: float, hit: float | None) -> None:
        memory = getattr(index, "bytes_per_descriptor", None)
        rows.append(
            {
                "map_size": size,
                "index": name,
                "fit_s": fit_s,
                "query_ms": ms,
                "recall_at_1": hit,
                "bytes_per_descriptor": memory,
            }
        )
        hit_text = "" if hit is None else f"{hit:.3f}"
        memory_text = "" if memory is None else f"{memory:.0f}"
        print(
            f"{size:>9} {name:<34} {fit_s:>8.1f} {ms:>9.2f} {hit_text:>7} {memory_text:>7}",
            flush=True,
        )

    print(f"{'N':>9} {'index':<34} {'fit s':>8} {'query ms':>9} {'recall':>7} {'B/desc':>7}")
    for size in args.sizes:
        features = random_descriptors(size, args.dim, seed=size)
        queries = random_descriptors(args.queries, args.dim, seed=1)
        flat = FaissIndex(kind="flat")
        fit_s = timed_fit(flat, features)
        truth = flat.neighbours(queries, 1)[1][:, 0]
        record(size, "faiss flat (exact)", fit_s, flat, query_ms(flat, queries), 1.0)
        del flat
        if size <= args.max_exhaustive and "exact" in args.only:
            exhaustive = ExhaustiveIndex()
            fit_s = timed_fit(exhaustive, features)
            hit = float(np.mean(exhaustive.nearest(queries)[1] == truth))
            record(
                size,
                "exhaustive (numpy float64)",
                fit_s,
                exhaustive,
                query_ms(exhaustive, queries),
                hit,
            )
            del exhaustive
            kmeans = KMeansIndex(k=40, n_init=1)
            fit_s = timed_fit(kmeans, features)
            record(size, "kmeans k=40 (paper)", fit_s, kmeans, query_ms(kmeans, queries), None)
            del kmeans
        gc.collect()
        nlist = max(1, round(size**0.5))
        if "ivf" in args.only:
            ivf = FaissIndex(kind="ivf", nlist=nlist)
            fit_s = timed_fit(ivf, features)
            for nprobe in args.nprobe:
                ivf.nprobe = nprobe
                ivf._configure_search()
                name = f"faiss ivf nlist={nlist} nprobe={nprobe}"
                record(size, name, fit_s, ivf, query_ms(ivf, queries), recall(ivf, queries, truth))
            del ivf
            gc.collect()
        if size <= args.max_hnsw and "hnsw" in args.only:
            hnsw = FaissIndex(kind="hnsw")
            fit_s = timed_fit(hnsw, features)
            for ef in args.ef_search:
                hnsw.ef_search = ef
                hnsw._configure_search()
                name = f"faiss hnsw M=32 ef_search={ef}"
                record(
                    size, name, fit_s, hnsw, query_ms(hnsw, queries), recall(hnsw, queries, truth)
                )
            del hnsw
            gc.collect()
        for key, name, options in (
            ("float16", "faiss flat float16", {"precision": "float16"}),
            ("pca", f"faiss flat pca_dim={args.pca_dim}", {"pca_dim": args.pca_dim}),
        ):
            if key not in args.only:
                continue
            index = FaissIndex(**options)
            fit_s = timed_fit(index, features)
            record(
                size, name, fit_s, index, query_ms(index, queries), recall(index, queries, truth)
            )
            del index
            gc.collect()
        del features
        gc.collect()
        report = {
            "dim": args.dim,
            "queries": args.queries,
            "machine": platform.processor() or platform.machine(),
            "rows": rows,
        }
        write_json(report, args.out)  # after every size: a later one may not fit


if __name__ == "__main__":
    main()
