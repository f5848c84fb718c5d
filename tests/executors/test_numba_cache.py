"""A numba cache folder per worker process (polarface.executors.numba_cache): each live process gets its
own slot, a process keeps it, a freed slot is reused; an already imported numba follows it."""

from __future__ import annotations

import subprocess
import sys

_CLAIM = (
    "import sys, numba; from polarface.executors.numba_cache import claim_numba_cache; "
    "folder = claim_numba_cache(sys.argv[1]); "
    "print(folder, claim_numba_cache(sys.argv[1]) == folder, numba.config.CACHE_DIR == folder, flush=True); "
    "sys.stdin.read()"
)


def _claim(base, stdin: str = "") -> list[str]:
    done = subprocess.run([sys.executable, "-c", _CLAIM, str(base)], input=stdin, capture_output=True,
                          text=True, timeout=120, check=True)
    return done.stdout.split()


def test_each_live_process_claims_its_own_numba_cache_and_a_freed_one_is_reused(tmp_path):
    holder = subprocess.Popen([sys.executable, "-c", _CLAIM, str(tmp_path)], stdin=subprocess.PIPE,
                              stdout=subprocess.PIPE, text=True)
    try:
        first = holder.stdout.readline().split()
        second = _claim(tmp_path)  # while the first process holds worker-0
    finally:
        holder.communicate("", timeout=120)
    third = _claim(tmp_path)  # the first process has ended: its slot is free again
    assert first == [str(tmp_path / "worker-0"), "True", "True"]
    assert second == [str(tmp_path / "worker-1"), "True", "True"]
    assert third == first
