"""Compare the tables of two results folders by content: every Parquet and CSV file.

Usage: python ci/compare-results.py DIR_A DIR_B

Both folders must hold the same set of tables (*.parquet, *.csv, *.tsv under any subfolder,
except benchmarks/ and logs/, whose timings differ from run to run). Each pair is read with
pandas and compared with pandas.testing.assert_frame_equal: same columns (in any order), same
rows in the same order, same dtypes, same values (floats exactly, NaN equal to NaN). Prints one
line per table and a verdict; exits 1 on any difference.
"""

from __future__ import annotations

import sys
from pathlib import Path

import pandas as pd

SKIP_DIRS = {"benchmarks", "logs"}
SUFFIXES = {".parquet", ".csv", ".tsv"}


def tables(root: Path) -> set[Path]:
    return {
        p.relative_to(root)
        for p in root.rglob("*")
        if p.is_file() and p.suffix in SUFFIXES and not (set(p.relative_to(root).parts[:-1]) & SKIP_DIRS)
    }


def read(path: Path) -> pd.DataFrame:
    if path.suffix == ".parquet":
        return pd.read_parquet(path)
    return pd.read_csv(path, sep="\t" if path.suffix == ".tsv" else ",")


def compare(a: Path, b: Path) -> list[str]:
    """Differences between the tables of folders a and b, one line each (empty: identical)."""
    fails: list[str] = []
    ta, tb = tables(a), tables(b)
    for rel in sorted(ta - tb):
        fails.append(f"{rel}: only in {a}")
    for rel in sorted(tb - ta):
        fails.append(f"{rel}: only in {b}")
    for rel in sorted(ta & tb):
        da, db = read(a / rel), read(b / rel)
        if sorted(map(str, da.columns)) != sorted(map(str, db.columns)):
            fails.append(f"{rel}: columns differ: {list(da.columns)} vs {list(db.columns)}")
            continue
        # Column order is not meaningful; row order is (tables are written sorted).
        da, db = da[sorted(da.columns, key=str)], db[sorted(db.columns, key=str)]
        try:
            pd.testing.assert_frame_equal(da, db, check_exact=True)
        except AssertionError as exc:
            first = " ".join(str(exc).split())[:300]
            fails.append(f"{rel}: {first}")
    return fails


def main(argv: list[str]) -> int:
    if len(argv) != 2:
        print(__doc__.strip().splitlines()[2], file=sys.stderr)
        return 2
    a, b = Path(argv[0]), Path(argv[1])
    for d in (a, b):
        if not d.is_dir():
            print(f"compare-results: {d}: not a folder", file=sys.stderr)
            return 2
    n = len(tables(a) | tables(b))
    if n == 0:
        print(f"compare-results: no tables under {a} or {b}", file=sys.stderr)
        return 1
    fails = compare(a, b)
    for line in fails:
        print(f"DIFFERENT {line}")
    if fails:
        print(f"compare-results: {len(fails)} of {n} tables differ between {a} and {b}")
        return 1
    print(f"compare-results: all {n} tables identical between {a} and {b}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
