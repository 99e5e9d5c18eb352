"""Shared by the benchmark scripts: machine description and writing a table into docs/benchmarks.md."""
from __future__ import annotations

import argparse
import contextlib
import os
import platform
import re
import resource
import shlex
import subprocess
import sys
import tempfile
import warnings
from pathlib import Path
from unittest import mock

import cv2
import numpy as np
import torch
from torch._subclasses.fake_tensor import FakeTensorMode

from diff4splat import generate
from diff4splat.io import save_image
from diff4splat.pipeline import Diff4SplatPipeline, load_model
from models import dit as dit_module
from models.bundle import DEFAULT_CONFIG, load_config
from models.dit import VideoDiT

BENCHMARKS_MD = Path(__file__).resolve().parent.parent / "docs" / "benchmarks.md"


def repo_relative(source: str) -> str:
    """A weights path as written in the docs: relative to the repository root when inside it."""
    root = str(Path(__file__).resolve().parent.parent) + "/"
    return source.replace(root, "")


def machine() -> str:
    """One line: CPU model, cores, torch version and threads."""
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return (f"{cpu}, {os.cpu_count()} cores, torch {torch.__version__} "
            f"({torch.get_num_threads()} threads), Python {platform.python_version()}")


def peak_rss_mb() -> float:
    """Peak resident set size of this process so far, MiB (Linux ru_maxrss is in KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


_PEAK_STARTER = """
import os, subprocess, sys, time
report, limit = sys.argv[1], float(sys.argv[2])
child = subprocess.Popen(sys.argv[3:])
end = time.monotonic() + limit
while True:
    pid, status, usage = os.wait4(child.pid, os.WNOHANG)
    if pid:
        break
    if time.monotonic() > end:
        child.kill()
        _, status, usage = os.wait4(child.pid, 0)
        open(report, "w").write(f"{usage.ru_maxrss} timeout")
        sys.exit(124)
    time.sleep(0.01)
code = os.waitstatus_to_exitcode(status)
open(report, "w").write(f"{usage.ru_maxrss} {code}")
sys.exit(code if code >= 0 else 128 - code)
"""
"""Starts a command, waits for it (at most ``argv[2]`` seconds, then kills it) and writes its peak resident memory
(KiB) and exit code, or ``timeout``, to the file ``argv[1]``."""


def run_with_peak_memory(argv: list[str], timeout: float | None = None,
                         **run_kwargs) -> tuple[subprocess.CompletedProcess, int]:
    """Run ``argv`` to its end (``subprocess.run`` with ``run_kwargs``: ``env``, ``capture_output``…; after
    ``timeout`` seconds it is killed); returns the completed process and the command's own peak resident memory,
    bytes (Linux).

    The command is started by a small Python process (:data:`_PEAK_STARTER`): a child's ``ru_maxrss``
    (``os.wait4``, ``RUSAGE_SELF`` in the child) counts its parent's peak as well, since Linux carries the peak of
    the memory map it replaces at ``exec`` into the new program's. Started straight from a pytest worker after
    hundreds of tests, ``generate --device cpu`` reported that worker's 2.72 GB against its own 1.34 GB
    (measured on the same machine, Intel Xeon, torch 2.11.0+cu130). The returncode is the command's
    (``-N`` for signal N).

    Raises:
        RuntimeError: the command could not be started (no such program).
        subprocess.TimeoutExpired: ``timeout`` passed; the command was killed.
    """
    with tempfile.TemporaryDirectory() as tmp:
        report = Path(tmp) / "peak"
        limit = "inf" if timeout is None else str(timeout)
        done = subprocess.run([sys.executable, "-c", _PEAK_STARTER, str(report), limit, *argv], **run_kwargs)
        if not report.is_file():
            raise RuntimeError(f"{argv[0]} did not start (its starter exited with {done.returncode})")
        kib, code = report.read_text().split()
    if code == "timeout":
        raise subprocess.TimeoutExpired(argv, timeout, done.stdout, done.stderr)
    done.args, done.returncode = argv, int(code)
    return done, int(kib) * 1024


@contextlib.contextmanager
def fake_dit_step(config: str, ff_chunk_tokens: int | None, dtype: torch.dtype = torch.bfloat16,
                  device: str = "cpu"):
    """``config``'s DiT built in ``dtype`` under torch's ``FakeTensorMode`` on ``device`` (shapes, dtypes and
    strides; no storage, no GPU) with the inputs of one sampling step at the config's frames and size and a
    full-length prompt. Yields ``(dit, inputs, tokens)``; run ``dit(*inputs)`` inside. The default dtype is restored
    after."""
    cfg = load_config(config)
    vae, dit_cfg = cfg.vae, cfg.dit
    n = vae.num_latent_frames(cfg.num_frames)
    h, w = cfg.height // vae.spatial_factor, cfg.width // vae.spatial_factor
    p = dit_cfg.patch_size
    previous = torch.get_default_dtype()
    torch.set_default_dtype(dtype)
    try:
        # σ's range check reads a value; fake tensors have none (the shapes are right by construction)
        with FakeTensorMode(), torch.device(device), mock.patch.object(dit_module, "check_dit_inputs", lambda *a: None):
            dit = VideoDiT(dit_cfg).eval()
            dit.ff_chunk_tokens = ff_chunk_tokens
            c = dit_cfg.latent_channels
            inputs = (torch.randn(1, c, n, h, w), torch.ones(1), torch.randn(1, c, 1, h, w),
                      torch.randn(1, dit_cfg.camera_channels, n, h, w),
                      torch.randn(1, cfg.text_encoder.max_length, dit_cfg.text_dim))
            yield dit, inputs, n * h * w // (p[0] * p[1] * p[2])
    finally:
        torch.set_default_dtype(previous)


def markdown_table(header: list[str], rows: list[list]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---:" if i else "---" for i in range(len(header))) + "|"]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return "\n".join(lines)


def markdown_rows(text: str) -> list[dict[str, str]]:
    """The rows of the first table in ``text`` (as :func:`markdown_table` writes it), each ``{column: cell}``
    with the cells stripped; [] where there is no table."""
    lines = [line for line in text.splitlines() if line.startswith("|")]

    def cells(line: str) -> list[str]:
        return [c.strip() for c in line.strip().strip("|").split("|")]

    header = cells(lines[0]) if lines else []
    return [dict(zip(header, cells(line), strict=False)) for line in lines[2:]]


def _markers(name: str) -> tuple[str, str]:
    return f"<!-- {name}:begin -->", f"<!-- {name}:end -->"


def read_section(name: str, path: Path = BENCHMARKS_MD) -> str | None:
    """The body of the section ``name`` (:func:`write_section`), or None where there is none."""
    begin, end = _markers(name)
    text = path.read_text() if path.exists() else ""
    found = re.search(re.escape(begin) + r"\n(.*?)\n" + re.escape(end), text, flags=re.S)
    return found.group(1) if found else None


def write_section(name: str, body: str, path: Path = BENCHMARKS_MD) -> None:
    """Replace (or append) the section between ``<!-- name:begin -->`` and ``<!-- name:end -->``."""
    begin, end = _markers(name)
    block = f"{begin}\n{body.strip()}\n{end}"
    text = path.read_text() if path.exists() else "# Benchmarks\n"
    if begin in text:
        text = re.sub(re.escape(begin) + ".*?" + re.escape(end), lambda _: block, text, flags=re.S)
    else:
        text = text.rstrip() + "\n\n" + block + "\n"
    tmp = path.with_suffix(".md.tmp")
    tmp.write_text(text)
    tmp.replace(path)


def publish(name: str, title: str, note: str, table: str, write: bool) -> str:
    """Print a section — ``### title``, the command line that made it, the machine, ``note``, the table — and with
    ``write`` put it into docs/benchmarks.md (:func:`write_section`); returns its body."""
    script = Path(sys.argv[0]).name
    body = (f"### {title}\n\n`python benchmarks/{script} {shlex.join(sys.argv[1:])}` on {machine()}. {note}\n\n"
            f"{table}\n")
    print(body)
    if write:
        write_section(name, body)
    return body


def load_pipeline(checkpoint, config: str):
    """``(Diff4SplatPipeline, weights source)`` of ``--checkpoint`` (None: the shipped weights of ``--config``),
    without the warnings of a missing checkpoint."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model, source = load_model(checkpoint, config)
    return Diff4SplatPipeline(model), source


def parse_pipeline_run(ap: argparse.ArgumentParser):
    """Add ``--checkpoint``, ``--device``, ``--label`` (the docs/benchmarks.md section's suffix), ``--note`` (a
    sentence for the table's note) and ``--write`` to ``ap``, parse it and load the pipeline on that device (without
    the warnings of a missing checkpoint): ``(args, diff4splat.generate.LoadedPipeline)``."""
    ap.add_argument("--checkpoint", type=Path, default=None)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--label", default=None, help="section name suffix in docs/benchmarks.md")
    ap.add_argument("--note", default="", help="a sentence on the data for the table's note (e.g. how it was used)")
    ap.add_argument("--write", action="store_true")
    args = ap.parse_args()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return args, generate.load_pipeline(args.checkpoint, device=args.device)


def held_out_run(description: str, data_help: str) -> tuple[argparse.Namespace, Diff4SplatPipeline, str]:
    """The command line of a benchmark over held-out sets (``--data DIR …``, ``--checkpoint``, ``--config``,
    ``--limit``, ``--write``) parsed, and its pipeline: ``(args, pipeline, weights source)``."""
    ap = argparse.ArgumentParser(description=description)
    ap.add_argument("--data", type=Path, nargs="+", required=True, help=data_help)
    ap.add_argument("--checkpoint", type=Path, default=None)
    ap.add_argument("--config", default=DEFAULT_CONFIG)
    ap.add_argument("--limit", type=int, default=None)
    ap.add_argument("--write", action="store_true")
    args = ap.parse_args()
    return (args, *load_pipeline(args.checkpoint, args.config))


def save_strip(path: Path, rows: dict[str, torch.Tensor], columns: int = 4, scale: int = 1) -> None:
    """An image (PNG or JPEG by ``path``'s suffix) of ``columns`` evenly spaced frames of each labelled row of
    (N, H, W, 3) frames in [0, 1], each enlarged ``scale``× (nearest neighbour: the pixels as they are)."""
    n = next(iter(rows.values())).shape[0]
    pick = np.linspace(0, n - 1, min(columns, n)).round().astype(int)
    lines = []
    for label, frames in rows.items():
        line = np.concatenate([(frames[i].clamp(0, 1).numpy() * 255).astype(np.uint8) for i in pick], axis=1)
        line = line.repeat(scale, axis=0).repeat(scale, axis=1)
        line = np.ascontiguousarray(line)
        cv2.putText(line, label, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 0), 1, cv2.LINE_AA)
        lines.append(line)
    save_image(path, np.concatenate(lines, axis=0))
