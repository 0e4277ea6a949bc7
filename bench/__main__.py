"""Run all benchmarks (or those named on the command line: python -m bench fpm fem).

What a module records (:func:`bench.results.record`) is written to ``bench/results/NAME.json``
when it ends (:func:`bench.results.save_all`); ``python -m bench.render`` then renders the
manual's benchmark pages and the README's headline figures from those files.
"""

import importlib
import pkgutil
import sys
import time

import bench
from bench import results


def main() -> None:
    wanted = sys.argv[1:]
    names = sorted(
        m.name for m in pkgutil.iter_modules(bench.__path__) if m.name.startswith("bench_")
    )
    for name in names:
        if wanted and name.removeprefix("bench_") not in wanted:
            continue
        print(f"\n=== {name} ===", flush=True)
        t0 = time.perf_counter()
        importlib.import_module(f"bench.{name}").main()
        print(f"({name}: {time.perf_counter() - t0:.1f} s)", flush=True)
        for path in results.save_all(f"python -m bench {name.removeprefix('bench_')}"):
            print(f"(results: {path.relative_to(results.ROOT)})", flush=True)


if __name__ == "__main__":
    main()
