"""Assemble a model from networks of several checkpoints: ``python -m training.compose``.

``python -m training.compose --config base --out runs/init/model vae=models/weights/tiny ldrm=runs/ldrm/model``
builds the model of ``--config`` with each named network taken from a checkpoint folder (warm starts; networks
trained side by side). A taken network keeps its checkpoint's config, overridden by the fields the target YAML sets
for it; its weights load strictly except zero-initialised layers it lacks (:data:`ZERO_INIT_PREFIXES`). ``--reinit
ldrm.head`` (network.prefix) starts those parameters from their initialisation instead.
"""
from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

from diff4splat.io.structured import read_yaml
from diff4splat.utils.errors import run_cli
from models.bundle import NETWORKS, Diff4SplatModel, config_path, load_config
from models.pretrained import config_from_dict

__all__ = ["compose", "main", "ZERO_INIT_PREFIXES"]

ZERO_INIT_PREFIXES = ("image_branch.", "motion.")
"""Parameter-name prefixes that may be missing from a taken network: zero-initialised layers whose output is 0."""


def compose(config: str | Path, sources: dict[str, str | Path], seed: int = 0, reinit: tuple[str, ...] = ()
            ) -> Diff4SplatModel:
    """The model (eval mode) of ``config`` (name or YAML path) with the networks of ``sources`` {network: folder}
    taken from those folders, the others seeded with ``seed``; ``reinit`` "network.prefix" entries keep their
    initialisation. Raises ValueError (unknown network, weights that do not fit), FileNotFoundError (missing config
    or folder)."""
    for name in sources:
        if name not in NETWORKS:
            raise ValueError(f"network: unknown network {name!r} (known: {', '.join(NETWORKS)})")
    target = load_config(config)
    explicit = read_yaml(config_path(config), "config")
    loaded = {folder: Diff4SplatModel.from_pretrained(folder) for folder in set(map(str, sources.values()))}
    for name, folder in sources.items():
        merged = {**dataclasses.asdict(getattr(loaded[str(folder)].config, name)), **explicit.get(name, {})}
        setattr(target, name, config_from_dict(type(getattr(target, name)), merged, f"{folder}/{name}"))
    target.validate()
    model = Diff4SplatModel.random(target, seed=seed)
    for name, folder in sources.items():
        fresh = tuple(r.partition(".")[2] for r in reinit if r.partition(".")[0] == name)
        state = {k: v for k, v in loaded[str(folder)].get_submodule(name).state_dict().items()
                 if not k.startswith(fresh)}  # startswith(()) is False: nothing dropped
        try:
            result = getattr(model, name).load_state_dict(state, strict=False)
        except RuntimeError as e:  # tensor shapes that differ from the composed config's
            raise ValueError(f"{name} from {folder}: weights do not fit the composed config: {e}") from None
        missing = [k for k in result.missing_keys if not k.startswith(ZERO_INIT_PREFIXES + fresh)]
        if missing or result.unexpected_keys:
            raise ValueError(f"{name} from {folder}: weights do not fit the composed config "
                             f"(missing {missing[:4]}, unexpected {result.unexpected_keys[:4]})")
    return model.eval()


def main(argv: list[str] | None = None) -> int:
    """``python -m training.compose`` (module docstring); exit code 2 with one line on bad input."""
    return run_cli("compose", lambda: _main(argv))


def _main(argv: list[str] | None) -> int:
    """Parse, compose and save."""

    ap = argparse.ArgumentParser(prog="python -m training.compose", description=__doc__.splitlines()[0])
    ap.add_argument("--config", required=True, help="model config name or YAML path")
    ap.add_argument("--out", required=True, type=Path, help="output model folder (replaced only if a saved model)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the networks not taken (default 0)")
    ap.add_argument("--reinit", action="append", default=[], metavar="NETWORK.PREFIX",
                    help="parameters to start from their initialisation, e.g. ldrm.head (repeatable)")
    ap.add_argument("take", nargs="+", metavar="NETWORK=FOLDER", help="network to take from a checkpoint folder")
    args = ap.parse_args(argv)
    sources = {}
    for item in args.take:
        name, sep, folder = item.partition("=")
        if not sep or not folder:
            raise ValueError(f"take: expected NETWORK=FOLDER, got {item!r}")
        sources[name] = folder
    for item in args.reinit:
        if item.partition(".")[0] not in sources or not item.partition(".")[2]:
            raise ValueError(f"--reinit: expected NETWORK.PREFIX of a taken network, got {item!r}")
    model = compose(args.config, sources, seed=args.seed, reinit=tuple(args.reinit))
    model.save_pretrained(args.out)
    counts = model.parameter_counts()
    print(f"wrote {args.out}: " + ", ".join(f"{k} {v:,}" for k, v in counts.items())
          + " — taken: " + ", ".join(f"{k} from {v}" for k, v in sources.items()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
