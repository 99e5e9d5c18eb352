"""The memory and output-size limits are the machine's own: the memory available now and the free space of the
output's disk (diff4splat/utils/limits.py), so the paper-size command of the README passes its checks on a GPU machine
(it was refused by the fixed 8 GiB / 4 GiB of a laptop) and a small disk refuses a request before any network runs.
"""
import os
import shutil
import subprocess
import sys
from pathlib import Path

import psutil
import pytest
import torch
from helpers import EXAMPLE_IMAGE

import diff4splat.utils.limits as limits
from diff4splat.cli import main
from diff4splat.generate import generate
from diff4splat.pipeline import Diff4SplatPipeline, load_model
from diff4splat.utils.errors import is_expected, one_line
from diff4splat.utils.limits import (
    LIMITS,
    OUTPUT_BYTES_PER_GAUSSIAN,
    OUTPUT_BYTES_PER_PIXEL,
    OUTPUT_DEFORMATION_BYTES_PER_GAUSSIAN,
    LimitError,
    available_memory,
    check_memory,
    check_output_size,
    free_disk,
)
from models.bundle import Diff4SplatModel, load_config

GiB = 1 << 30


class _Ran(Exception):
    """Raised in place of the networks: the request passed every check before them."""


def _ran(*args, **kwargs):
    raise _Ran


@pytest.fixture
def no_env(monkeypatch):
    """Neither limit's variable set: the machine's resources decide."""
    for name in ("memory_bytes", "output_bytes"):
        monkeypatch.delenv(LIMITS[name].env, raising=False)


def test_free_disk_is_the_free_space_of_the_nearest_existing_folder(tmp_path):
    assert free_disk(tmp_path / "not" / "yet" / "out") == pytest.approx(shutil.disk_usage(tmp_path).free,
                                                                         abs=64 << 20)
    assert free_disk(tmp_path / "out") != shutil.disk_usage(tmp_path).total  # free, not the disk's size
    assert free_disk("relative/out") == pytest.approx(shutil.disk_usage(os.getcwd()).free, abs=64 << 20)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc/meminfo")
def test_available_memory_is_what_the_process_holds_plus_memavailable():
    """The estimate is of the whole process's peak, checked after the networks are loaded: the bound is what the
    process holds plus Linux's MemAvailable (free + reclaimable page cache), not MemFree (which a full page cache
    drives to zero) nor MemTotal, nor MemAvailable alone (which would count the loaded weights twice)."""
    info = {k: int(v.split()[0]) * 1024 for k, v in
            (line.split(":", 1) for line in open("/proc/meminfo").read().splitlines())}
    rss = psutil.Process().memory_info().rss
    assert rss > 256 << 20  # torch alone: so MemAvailable alone would miss by more than the tolerance
    assert available_memory() == pytest.approx(info["MemAvailable"] + rss, abs=128 << 20)
    assert available_memory() < psutil.virtual_memory().total + rss


def test_output_size_is_checked_against_the_output_disk(tmp_path, monkeypatch, no_env):
    out = tmp_path / "{braces} and spaces"
    monkeypatch.setattr(limits, "free_disk", lambda path: 3 * GiB)
    est = check_output_size(17, 256, 256, gaussians=1_000_000, out=out)  # 1.9 GiB
    assert est == 17 * 256 * 256 * 16 + 18 * 1_000_000 * 112
    with pytest.raises(LimitError) as e:
        check_output_size(49, 512, 512, gaussians=3_479_808, knobs="--frames or --resolution", out=out)
    assert str(e.value) == (f"output of 49 frames at 512×512: estimated 18.3 GiB exceeds the 3.0 GiB free on the disk "
                            f"of {out} (lower --frames or --resolution, or set DIFF4SPLAT_MAX_OUTPUT_BYTES to a size "
                            "in bytes)")
    monkeypatch.setenv("DIFF4SPLAT_MAX_OUTPUT_BYTES", str(GiB))  # the variable wins over the disk
    with pytest.raises(LimitError, match=r"exceeds the limit of 1.0 GiB \(1073741824 bytes; .*to raise it\)"):
        check_output_size(17, 256, 256, gaussians=1_000_000, out=out)
    monkeypatch.delenv("DIFF4SPLAT_MAX_OUTPUT_BYTES")
    monkeypatch.setattr(limits, "free_disk", lambda path: None)  # not measurable: the fixed 4 GiB
    with pytest.raises(LimitError, match="exceeds the limit of 4.0 GiB"):
        check_output_size(49, 512, 512, gaussians=3_479_808, out=out)


def test_without_frame_plys_the_estimate_is_the_scene_ply_and_the_deformation(monkeypatch):
    """frames/ costs a PLY row per Gaussian and frame: without it, one row for scene.ply and the deformation's
    10 float32 per Gaussian and frame remain (each with margin), still above what is written."""
    monkeypatch.setenv("DIFF4SPLAT_MAX_OUTPUT_BYTES", str(1 << 50))
    F, G = 49, 3_479_808
    images = F * 512 * 512 * OUTPUT_BYTES_PER_PIXEL
    assert check_output_size(F, 512, 512, G) == images + (F + 1) * G * OUTPUT_BYTES_PER_GAUSSIAN
    without = check_output_size(F, 512, 512, G, frame_plys=False)
    assert without == images + G * (OUTPUT_BYTES_PER_GAUSSIAN + F * OUTPUT_DEFORMATION_BYTES_PER_GAUSSIAN)
    assert G * 17 * 4 + F * G * 10 * 4 < without - images < 0.45 * (check_output_size(F, 512, 512, G) - images)


def test_memory_is_checked_against_the_memory_available(monkeypatch, no_env):
    monkeypatch.setattr(limits, "available_memory", lambda: 12 * GiB)
    assert check_memory(11 * GiB, "x", "y") == 11 * GiB
    with pytest.raises(LimitError) as e:
        check_memory(13 * GiB, "49 frames at 512×512", "--frames or --resolution")
    assert str(e.value) == ("49 frames at 512×512: estimated peak memory 13.0 GiB exceeds the 12.0 GiB of memory "
                            "available to this process (lower --frames or --resolution, or set "
                            "DIFF4SPLAT_MAX_MEMORY_BYTES to a size in bytes)")
    monkeypatch.setenv("DIFF4SPLAT_MAX_MEMORY_BYTES", str(16 * GiB))  # the variable wins, above or below
    assert check_memory(13 * GiB, "x", "y") == 13 * GiB
    monkeypatch.delenv("DIFF4SPLAT_MAX_MEMORY_BYTES")
    monkeypatch.setattr(limits, "available_memory", lambda: None)  # not measurable: the fixed 8 GiB
    with pytest.raises(LimitError, match="exceeds the limit of 8.0 GiB"):
        check_memory(9 * GiB, "x", "y")


@pytest.mark.slow
@pytest.mark.parametrize("memory, disk, refused", [
    (120 * GiB, 60 * GiB, None),  # the H100 machine of issue 26: 128 GiB of memory, 64 GiB of disk
    (8 * GiB, 60 * GiB, "of memory available to this process"),  # a laptop: the scene's host copies alone ~13 GiB
    (120 * GiB, 10 * GiB, "free on the disk of"),  # a full disk: 18.3 GiB for 49 frames of 3.48 M Gaussian slots
    (120 * GiB, -10 * GiB, None),  # the same disk with --no-frame-plys (7.5 GiB): the README's command
])
def test_the_paper_size_request_passes_its_checks_where_the_machine_has_room(tmp_path, monkeypatch, no_env, memory,
                                                                             disk, refused):
    """`generate --config paper` (49 frames, 512²) was refused before any network ran by the fixed defaults
    (18.3 GiB of output against 4 GiB, 70.8 GB of memory against 8 GiB) on any machine: the README's paper-size
    command could not run. The paper model is built on the meta device (no memory); the networks are not run."""
    pipe = Diff4SplatPipeline(Diff4SplatModel.random(load_config("paper"), device="meta", dtype=torch.bfloat16),
                              device="meta")
    monkeypatch.setattr(Diff4SplatPipeline, "__call__", _ran)
    monkeypatch.setattr(limits, "available_memory", lambda: memory)
    monkeypatch.setattr(limits, "free_disk", lambda path: abs(disk))
    expected = _Ran if refused is None else LimitError
    with pytest.raises(expected, match=refused):
        generate(EXAMPLE_IMAGE, pipeline=pipe, out=tmp_path / "out", frame_plys=disk > 0)


def test_cli_refuses_a_request_its_output_disk_cannot_hold_before_the_networks_run(tmp_path, capsys, monkeypatch,
                                                                                   no_env):
    monkeypatch.setattr(Diff4SplatPipeline, "__call__", _ran)
    seen = []
    monkeypatch.setattr(limits, "free_disk", lambda path: seen.append(path) or 50 << 20)  # 50 MiB free
    out = tmp_path / "out"
    code = main(["generate", str(EXAMPLE_IMAGE), "--quiet", "--out", str(out)])
    err = [line for line in capsys.readouterr().err.splitlines() if not line.startswith("diff4splat: warning")]
    assert code == 2 and len(err) == 1, err
    assert err[0].startswith("diff4splat: error: output of 17 frames at 256×256: estimated 218.3 MiB exceeds the "
                             f"50.0 MiB free on the disk of {out}"), err  # it said "0.0 GiB free"
    assert seen == [out] and not out.exists()


@pytest.mark.parametrize("dtype, needle", [(None, "the weights of 16,834,223,193 parameters in float32: estimated "
                                                  "peak memory 62.7 GiB"),
                                           (torch.bfloat16, "in bfloat16: estimated peak memory 31.4 GiB")])
def test_a_model_too_large_for_the_memory_is_refused_before_it_is_built(monkeypatch, no_env, dtype, needle):
    """`generate --config paper` on a laptop: the random paper model (67.3 GB in float32, 33.7 GB in bfloat16) is
    refused when counted on the meta device, before any weight is allocated (it used to be built, then the
    request's memory check came too late)."""
    monkeypatch.setattr(limits, "available_memory", lambda: 16 * GiB)
    allocated = []
    monkeypatch.setattr(torch.nn.Linear, "reset_parameters", lambda self: allocated.append(self.weight.device.type))
    with pytest.raises(LimitError) as e:
        load_model(config="paper", dtype=dtype)
    assert needle in str(e.value) and "16.0 GiB of memory available to this process" in str(e.value)
    assert ("(lower the weights' dtype (--dtype bfloat16 halves float32) or the model size (--config), or set "
            "DIFF4SPLAT_MAX_MEMORY_BYTES" in str(e.value)) == (dtype is None)
    assert "(lower the model size (--config), or set" in str(e.value) or dtype is None
    assert set(allocated) <= {"meta"}


def _cgroup(folder, limit, usage, inactive, v1=False):
    folder.mkdir(parents=True, exist_ok=True)
    (folder / ("memory.limit_in_bytes" if v1 else "memory.max")).write_text(f"{limit}\n")
    (folder / ("memory.usage_in_bytes" if v1 else "memory.current")).write_text(f"{usage}\n")
    key = "total_inactive_file" if v1 else "inactive_file"
    (folder / "memory.stat").write_text(f"anon 123\n{key} {inactive}\nfile 456\n")


def test_cgroup_room_is_the_least_limit_minus_working_set_along_the_hierarchy(tmp_path):
    """A container or SLURM job limits memory below the machine's: MemAvailable alone would let a job take the
    host's memory and be killed. Room = limit − (usage − inactive file cache), the least over the cgroup and its
    parents; cgroup v2 and v1 layouts; "max" / v1's 2⁶³ mean no limit."""
    proc = tmp_path / "cgroup"
    root = tmp_path / "fs"
    proc.write_text("0::/user.slice/job1\n")
    _cgroup(root / "user.slice" / "job1", 8 * GiB, 4 * GiB, GiB)
    _cgroup(root / "user.slice", "max", 30 * GiB, 0)
    assert limits.cgroup_room(proc, root) == 5 * GiB
    _cgroup(root / "user.slice", 6 * GiB, 5 * GiB + GiB // 2, 0)  # a parent with less room: it binds
    assert limits.cgroup_room(proc, root) == GiB // 2
    _cgroup(root / "user.slice", "max", 30 * GiB, 0)
    _cgroup(root / "user.slice" / "job1", "max", 4 * GiB, GiB)
    assert limits.cgroup_room(proc, root) is None  # no limit anywhere
    proc.write_text("0::/\n")  # a cgroup namespace: the process's cgroup is the mount's root
    _cgroup(root, 2 * GiB, GiB, 0)
    assert limits.cgroup_room(proc, root) == GiB
    proc.write_text("12:pids:/x\n4:memory:/slurm/uid_1/job_2\n0::/\n")  # v1 (hybrid: the memory line wins)
    _cgroup(root / "memory" / "slurm" / "uid_1" / "job_2", 16 * GiB, 10 * GiB, 2 * GiB, v1=True)
    _cgroup(root / "memory" / "slurm", 9223372036854771712, 40 * GiB, 0, v1=True)
    assert limits.cgroup_room(proc, root) == 8 * GiB
    assert limits.cgroup_room(tmp_path / "no_such_file", root) is None


def test_available_memory_is_held_by_the_cgroup_limit(monkeypatch):
    rss = psutil.Process().memory_info().rss
    monkeypatch.setattr(limits, "cgroup_room", lambda: GiB)
    assert available_memory() == pytest.approx(rss + GiB, abs=64 << 20)
    monkeypatch.setattr(limits, "cgroup_room", lambda: 1 << 50)  # more than the machine: the machine binds
    assert available_memory() < psutil.virtual_memory().total + rss


TORCH_OOM = ("CUDA out of memory. Tried to allocate 20.00 GiB. GPU 0 has a total capacity of 79.19 GiB of which 3.06 "
             "GiB is free. Including non-PyTorch memory, this process has 76.12 GiB memory in use. Of the allocated "
             "memory 75.50 GiB is allocated by PyTorch, and 1.2 MiB is reserved by PyTorch but unallocated. If "
             "reserved but unallocated memory is large try setting PYTORCH_CUDA_ALLOC_CONF=expandable_segments:True "
             "to avoid fragmentation.  See documentation for Memory Management  "
             "(https://pytorch.org/docs/stable/notes/cuda.html#environment-variables)")


def test_a_gpu_out_of_memory_is_one_line_naming_what_lowers_it(tmp_path, capsys, monkeypatch):
    """`generate --config paper` without `--offload model` on a 24 GB GPU: torch's OutOfMemoryError (a
    RuntimeError, which would print a traceback) is an expected failure: one line with what was asked and what
    is free, the flags that lower it, exit 2, nothing written."""
    oom = torch.OutOfMemoryError(TORCH_OOM)
    assert is_expected(oom) and not is_expected(RuntimeError("a bug"))
    assert one_line(oom) == ("CUDA out of memory. Tried to allocate 20.00 GiB. GPU 0 has a total capacity of 79.19 GiB "
                             "of which 3.06 GiB is free. Lower the request (--frames, --resolution), or use --offload "
                             "model or --dtype bfloat16 where the command has them")

    def out_of_memory(*args, **kwargs):
        raise torch.OutOfMemoryError(TORCH_OOM)

    monkeypatch.setattr(Diff4SplatPipeline, "__call__", out_of_memory)
    out = tmp_path / "out"
    code = main(["generate", str(EXAMPLE_IMAGE), "--quiet", "--frames", "5", "--out", str(out)])
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert code == 2 and err == [f"diff4splat: error: {one_line(oom)}"] and not out.exists()


def test_memory_caps_count_the_process_ulimits_and_the_message_names_the_tightest(monkeypatch, no_env):
    """``ulimit -v`` (RLIMIT_AS) bounds the address space: what the process may still allocate is the limit less its
    virtual size now, not the machine's available memory (issue 61: ``generate --frames 201`` under an 8 GB
    ``ulimit -v`` ran 75 s against MemAvailable, then died in an allocation)."""
    mem = psutil.Process().memory_info()
    caps = {"RLIMIT_AS": mem.vms + 2 * GiB, "RLIMIT_DATA": None}
    monkeypatch.setattr(limits, "_rlimit", lambda which: caps[which])
    monkeypatch.setattr(limits, "cgroup_room", lambda: None)
    got = limits.memory_caps()
    assert got["address-space limit (ulimit -v, RLIMIT_AS)"] == pytest.approx(2 * GiB, abs=64 << 20)
    assert limits.available_memory() == pytest.approx(psutil.Process().memory_info().rss + 2 * GiB, abs=64 << 20)
    with pytest.raises(LimitError, match=r"exceeds the .* GiB this process may still use under its address-space "
                                         r"limit \(ulimit -v, RLIMIT_AS\)"):
        check_memory(mem.rss + 3 * GiB, "--frames 201 at 256×256", "--frames")
    caps["RLIMIT_DATA"] = (mem.data if hasattr(mem, "data") else 0) + GiB  # the data segment is tighter now
    if hasattr(mem, "data"):
        assert limits.tightest_memory_cap() == "data-segment limit (ulimit -d, RLIMIT_DATA)"
    caps.update(RLIMIT_AS=None, RLIMIT_DATA=None)
    monkeypatch.setattr(limits, "cgroup_room", lambda: GiB // 2)  # a container's memory.max
    with pytest.raises(LimitError, match=r"under its cgroup memory\.max"):
        check_memory(psutil.Process().memory_info().rss + GiB, "x", "y")


@pytest.mark.slow
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="bash's ulimit -v")
def test_generate_under_a_real_ulimit_v_is_refused_before_the_work_naming_the_cap(tmp_path):
    """A child process under ``ulimit -v 8000000`` (8 GB of address space), as in issue 61: ``generate --frames
    201`` is refused with one line naming RLIMIT_AS, exit 2, and writes nothing."""
    out = tmp_path / "out"
    cmd = (f"ulimit -v 8000000 && exec {sys.executable} -m diff4splat.cli generate {EXAMPLE_IMAGE} --frames 201 "
           f"--quiet --out {out}")
    env = {k: v for k, v in os.environ.items() if not k.startswith("DIFF4SPLAT_MAX_")}
    r = subprocess.run(["bash", "-c", cmd], capture_output=True, text=True, timeout=300, env=env)
    assert r.returncode == 2, r.stderr[-2000:]
    assert r.stderr.count("\n") == 1 and "ulimit -v, RLIMIT_AS" in r.stderr, r.stderr
    assert not out.exists()


@pytest.mark.slow
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="bash's ulimit -v")
@pytest.mark.parametrize("command", ["diff4splat generate {photo} --quiet --out {out}",
                                     "data_prep synth --scenes 1 --out {out}",
                                     "{python} -m training.train --config train_stage1 --run-dir {out}"])
def test_a_ulimit_v_too_small_to_load_torch_is_one_line_at_import(tmp_path, command):
    """``ulimit -v 1000000`` (0.95 GiB): ``import cv2`` after torch segfaulted (exit −11, nothing on stderr); now
    the package's first import refuses it in one line naming the limit, exit 2, for the console scripts and
    ``python -m``; imported as a library it is an ImportError."""
    bin_dir = Path(sys.executable).parent
    cmd = command.format(photo=EXAMPLE_IMAGE, out=tmp_path / "out", python=sys.executable)
    first, rest = cmd.split(" ", 1)
    if not first.startswith("/"):
        if not (bin_dir / first).is_file():
            pytest.skip(f"no {first} console script beside {sys.executable}")
        first = str(bin_dir / first)
    r = subprocess.run(["bash", "-c", f"ulimit -v 1000000 && exec {first} {rest}"], capture_output=True, text=True,
                       timeout=120)
    name = {"diff4splat": "diff4splat", "data_prep": "data_prep"}.get(Path(first).name, "train")
    assert r.returncode == 2 and r.stderr.count("\n") == 1, (r.returncode, r.stderr[-2000:])
    assert r.stderr.startswith(f"{name}: error: this process may map 0.95 GiB (ulimit -v, RLIMIT_AS)"), r.stderr
    assert not (tmp_path / "out").exists()
    lib = subprocess.run(["bash", "-c", f"ulimit -v 1000000 && exec {sys.executable} -c 'import diff4splat'"],
                         capture_output=True, text=True, timeout=120)
    assert lib.returncode == 1 and lib.stderr.strip().splitlines()[-1].startswith(
        "ImportError: diff4splat: this process may map 0.95 GiB"), lib.stderr
