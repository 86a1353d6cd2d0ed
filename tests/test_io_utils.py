"""I/O helpers: atomic writes (a reader sees the old output or the new one, and a failure leaves nothing
behind) and the machine record beside every result."""

from __future__ import annotations

from pathlib import Path

import pytest

from ghsplat_jax.io_utils import atomic_path, atomic_write, machine_info, machine_kind, one_machine


def test_atomic_write_replaces_a_file_only_on_success(tmp_path):
    target = tmp_path / "a.txt"
    with atomic_write(target, "w") as fh:
        fh.write("one")
    assert target.read_text() == "one" and (target.stat().st_mode & 0o777) != 0o600
    with pytest.raises(RuntimeError):
        with atomic_write(target, "w") as fh:
            fh.write("half")
            raise RuntimeError("crash")
    assert target.read_text() == "one"
    assert [p.name for p in tmp_path.iterdir()] == ["a.txt"]


def test_atomic_path_writes_and_replaces_folders(tmp_path):
    target = tmp_path / "model"
    for n in (2, 1):
        with atomic_path(target) as tmp:
            assert tmp.name == "model" and not tmp.exists()
            tmp.mkdir()
            for i in range(n):
                (tmp / f"{i}.bin").write_bytes(b"x")
    assert sorted(p.name for p in target.iterdir()) == ["0.bin"]  # the old folder's files are gone
    with pytest.raises(FileNotFoundError, match="no output"):
        with atomic_path(tmp_path / "never"):
            pass
    assert [p.name for p in tmp_path.iterdir()] == ["model"]


@pytest.mark.skipif(not Path("/proc/cpuinfo").is_file(), reason="no /proc/cpuinfo (not Linux)")
def test_machine_info_names_the_cpu_on_linux():
    # platform.processor() is empty on Linux; a result must still say which CPU (and vector units) made it.
    info = machine_info()
    assert info["processor"].strip()
    assert isinstance(info["cpu_simd"], list) and all(isinstance(f, str) for f in info["cpu_simd"])


def test_code_revision_is_read_once_so_a_checkout_moved_under_a_run_does_not_rename_its_code(monkeypatch):
    import subprocess

    from ghsplat_jax.io_utils import code_revision

    first = code_revision()

    def moved(*args, **kwargs):  # git would now name another commit
        return subprocess.CompletedProcess(args, 0, stdout="f" * 40 + "\n", stderr="")

    monkeypatch.setattr(subprocess, "run", moved)
    assert code_revision() == first


def test_a_row_without_a_machine_record_joins_its_devices_main_host():
    """A row from before rows recorded their machine is timed with the host most rows of its device
    name, never with another device's; a row's own record always wins."""
    amd, intel = "AMD EPYC x2, cpu", "Intel Xeon x2, cpu"
    old, gpu = {"variant": "compact", "device": "cpu"}, {"variant": "compact", "device": "NVIDIA H200"}
    rows = [old, gpu, {"host": amd}, {"host": amd}, {"host": intel}]
    assert [machine_kind(r, rows) for r in rows] == ["AMD EPYC x2, cpu", "NVIDIA H200", amd, amd, intel]
    assert one_machine(rows) == (amd, [old, rows[2], rows[3]])
    assert one_machine(rows, prefer=intel) == (intel, [rows[4]])
    assert one_machine([old]) == ("cpu", [old])  # nothing to join: its device
