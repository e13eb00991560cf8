"""Read a user's CSV file into a :class:`pandas.DataFrame`, every failure one clear error.

The campaign tables (:mod:`waveforest.io.tables`) and trajectories
(:mod:`waveforest.io.trajectory`) open their files here; each checks its columns itself.
"""

from __future__ import annotations

import os
from pathlib import Path

import pandas as pd


def read_csv_file(path: str | os.PathLike, error: type[Exception], *, what: str = "file", **read_csv) -> pd.DataFrame:
    """The CSV file ``path`` with its column names stripped of surrounding blanks.

    Parameters
    ----------
    path : str or PathLike
    error : Exception subclass
        Raised, with a message starting ``"{path}: "``, when ``path`` is not a regular file
        (``no such {what}``) or not a readable CSV file (a parser error, no content, or
        bytes that are not UTF-8).
    what : str
        What the file is, for the message.
    **read_csv
        Passed to :func:`pandas.read_csv`.
    """
    path = Path(path)
    if not path.is_file():
        raise error(f"{path}: no such {what}")
    try:
        df = pd.read_csv(path, **read_csv)
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as exc:
        raise error(f"{path}: not a readable CSV file ({exc})") from None
    df.columns = [str(c).strip() for c in df.columns]
    return df
