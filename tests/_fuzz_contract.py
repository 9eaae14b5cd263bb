"""The contract every file reader keeps on bad input, checked through the real ``cdpr`` entry point:
exit 0 or 2, never a traceback; on 2 exactly one stderr line naming the bad file, no output file
created and every file that existed before unchanged.  Shared by ``tests/test_fuzz_*.py``."""

from __future__ import annotations

import os
from pathlib import Path

from hypothesis import HealthCheck, settings
from hypothesis import strategies as st

from cdpr.pipelines.cli import main

EXAMPLES = int(os.environ.get("CDPR_FUZZ_EXAMPLES", "50"))
"""Examples per fuzzer: 50 keeps ``make test`` fast; ``CDPR_FUZZ_EXAMPLES=2000`` for a deep run."""
RANDOM = os.environ.get("CDPR_FUZZ_RANDOM", "") not in ("", "0")
"""Derandomized by default (the same cases in every run); ``CDPR_FUZZ_RANDOM=1`` searches anew."""
FUZZ = settings(
    max_examples=EXAMPLES,
    derandomize=not RANDOM,
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture],
)


def snapshot(folder: Path) -> dict[str, bytes]:
    return {
        p.relative_to(folder).as_posix(): p.read_bytes() for p in folder.rglob("*") if p.is_file()
    }


def check_cli(capsys, argv: list[str], folder: Path, bad_file: Path, outputs: list[Path]) -> int:
    """Run ``cdpr argv`` with ``bad_file`` (in ``folder``) fuzzed; assert the contract."""
    before = snapshot(folder)
    capsys.readouterr()
    code = main(argv)
    err = capsys.readouterr().err
    assert code in (0, 2), (code, err)
    assert "Traceback" not in err, err
    if code == 2:
        lines = err.strip().splitlines()
        assert len(lines) == 1, lines
        assert str(bad_file) in lines[0], lines[0]
        for out in outputs:
            assert not out.exists(), out
        after = snapshot(folder)
        assert after == before, sorted(set(after) ^ set(before))
    return code


# Mutations of a valid text file: each keeps most of the file so the parser gets deep into it.
_VALUES = [
    "1e300", "-1e300", "nan", "inf", "-inf", "0", "-1", '"text"', "true", "[]", "[1, 2]",
    "[[1], [2]]", "{}", '""', "1e-320", "99999999999999999999999", "'x'", "[1, \"a\"]",
]  # fmt: skip


@st.composite
def mutated(draw, text: str, separators: str = "=,") -> bytes:
    """``text`` (UTF-8) with 1-3 random edits: a value replaced, bytes flipped or inserted
    (non-UTF-8 too), the file truncated, a line dropped or duplicated."""
    data = text.encode()
    for _ in range(draw(st.integers(1, 3))):
        op = draw(st.sampled_from(["value", "flip", "insert", "truncate", "drop", "dup"]))
        n = len(data)
        if op == "value":
            lines = data.split(b"\n")
            i = draw(st.integers(0, len(lines) - 1))
            line = lines[i]
            for sep in separators.encode():
                j = line.find(bytes([sep]))
                if j >= 0:
                    v = draw(st.sampled_from(_VALUES)).encode()
                    end = line.find(b",", j + 1) if sep == ord(",") else -1
                    lines[i] = line[: j + 1] + v + (line[end:] if end > 0 else b"")
                    break
            data = b"\n".join(lines)
        elif op == "flip" and n:
            k = draw(st.integers(0, n - 1))
            data = data[:k] + bytes([data[k] ^ draw(st.integers(1, 255))]) + data[k + 1 :]
        elif op == "insert":
            k = draw(st.integers(0, n))
            data = data[:k] + draw(st.binary(min_size=1, max_size=6)) + data[k:]
        elif op == "truncate" and n:
            data = data[: draw(st.integers(0, n - 1))]
        elif op in ("drop", "dup"):
            lines = data.split(b"\n")
            i = draw(st.integers(0, len(lines) - 1))
            lines[i : i + 1] = [] if op == "drop" else [lines[i], lines[i]]
            data = b"\n".join(lines)
    return data
