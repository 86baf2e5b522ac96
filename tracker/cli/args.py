"""argparse types and option groups shared by the commands."""
from __future__ import annotations

import argparse


def _number(kind, low: float, strict: bool, what: str):
    """An argparse type: a finite ``kind`` above ``low`` (or at least it, when not ``strict``)."""
    def parse(text: str):
        try:
            v = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"'{text}' is not {what}") from None
        if v != v or v in (float("inf"), float("-inf")) or (v <= low if strict else v < low):
            raise argparse.ArgumentTypeError(f"'{text}' is not {what}")
        return v
    return parse


positive_int = _number(int, 0, True, "a positive integer")
nonnegative_int = _number(int, 0, False, "an integer >= 0")
positive_float = _number(float, 0.0, True, "a positive number")
nonnegative_float = _number(float, 0.0, False, "a number >= 0")
finite_float = _number(float, float("-inf"), True, "a number")


def fraction(text: str) -> float:
    v = _number(float, 0.0, False, "a number from 0 to 1")(text)
    if v > 1:
        raise argparse.ArgumentTypeError(f"'{text}' is not a number from 0 to 1")
    return v


def shard_spec(text: str) -> tuple[int, int]:
    """'2/8' -> (2, 8): the K-th (from 0) of N parts."""
    try:
        k, n = (int(v) for v in text.split("/"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not K/N, e.g. 0/4") from None
    if not (n >= 1 and 0 <= k < n):
        raise argparse.ArgumentTypeError(f"'{text}': give K/N with 0 <= K < N, e.g. 0/4 ... 3/4")
    return k, n


def jpeg_quality(text: str) -> int:
    q = _number(int, 1, False, "a JPEG quality from 1 to 100")(text)
    if q > 100:
        raise argparse.ArgumentTypeError(f"'{text}' is not a JPEG quality from 1 to 100")
    return q


def id_list(text: str) -> list[int]:
    """'1,5,9' -> [1, 5, 9]."""
    try:
        ids = [int(x) for x in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not a comma-separated list of object ids, e.g. 1,5,9") from None
    return ids


def add_precision(s) -> None:
    from tracker.core.defaults import PRECISIONS
    s.add_argument("--precision", choices=PRECISIONS, default="auto",
                   help="arithmetic of the training passes: bf16 (bfloat16 autocast, faster where "
                        "the CPU has it natively), fp32, or auto (bf16 where native)")


def add_regressor_budget(s) -> None:
    s.add_argument("--reg-minutes", type=positive_float, default=5.0, help="time budget per MLP regressor")
    s.add_argument("--reg-epochs", type=positive_int, metavar="N",
                   help="train each MLP regressor for N epochs, whatever the time (reproducible; in place of --reg-minutes)")


def add_join(s, model_help: str, dest: str, from_help: str, required: bool = True) -> None:
    """The options of the join-* commands: the bundle that is kept, the bundles that join it, --out."""
    s.add_argument("--model", required=True, help=model_help)
    s.add_argument("--from", dest=dest, nargs="+", required=required, default=[], metavar="DIR", help=from_help)
    s.add_argument("--out", help="write the joined bundle here (default: in place)")
