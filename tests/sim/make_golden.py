"""Write ``data/golden.npz``: the figures `test_golden.py` compares the lockstep runs with.

Run from the repository:

    .venv/bin/python tests/sim/make_golden.py

Only when a change is meant to change the figures: see `test_golden.py`. The cases, and what of
a record is stored, are `test_golden.CASES` and `test_golden.record_arrays`. The file is written
byte for byte the same from the same figures (sorted keys, a fixed timestamp in the archive), so
regenerating it after a change that moves no figure leaves it unchanged in git.
"""

import io
import json
import os
import zipfile

os.environ.setdefault("OPENBLAS_CORETYPE", "Haswell")  # as tests/conftest.py

import numpy as np  # noqa: E402
from test_golden import CASES, GOLDEN, PLATFORM_KEY, fly, platform_fingerprint, record_arrays

ZIP_TIMESTAMP = (1980, 1, 1, 0, 0, 0)
"""The archive's member timestamp: the earliest a zip file holds, the same every time."""


def write_npz(path, arrays: dict[str, np.ndarray]) -> None:
    """Write `arrays` as a compressed ``.npz`` that `numpy.load` reads, reproducibly."""
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", compression=zipfile.ZIP_DEFLATED) as archive:
        for key in sorted(arrays):
            member = zipfile.ZipInfo(f"{key}.npy", date_time=ZIP_TIMESTAMP)
            member.compress_type = zipfile.ZIP_DEFLATED
            with archive.open(member, "w") as f:
                np.lib.format.write_array(f, arrays[key], allow_pickle=False)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(buffer.getvalue())


def main() -> None:
    arrays: dict[str, np.ndarray] = {}
    for case in CASES:
        rec = fly(case)
        for field, value in record_arrays(rec).items():
            arrays[f"{case.name}/{field}"] = value
        print(f"{case.name}: {len(rec.t_s)} periods, {len(rec.vehicle_ids)} vehicles")
    arrays[PLATFORM_KEY] = np.array(json.dumps(platform_fingerprint(), sort_keys=True))
    write_npz(GOLDEN, arrays)
    print(f"wrote {GOLDEN} ({GOLDEN.stat().st_size / 1024:.0f} KiB, {len(arrays)} arrays)")
    print(f"platform: {arrays[PLATFORM_KEY]}")


if __name__ == "__main__":
    main()
