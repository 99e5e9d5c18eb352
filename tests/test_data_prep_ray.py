"""``data_prep`` on Ray Data (``--engine ray``, :mod:`data_prep.engine`) on a local Ray that this module starts:
the same dataset, byte for byte, as ``--engine local --workers 1`` for ``synth``, ``convert --each`` and ``curate``;
two gloo ranks train on a Ray-curated dataset."""
from __future__ import annotations

import dataclasses
import json
import textwrap

import pytest
import yaml

ray = pytest.importorskip("ray", reason="the ray extra (diff4splat[ray]) is not installed")

from _data_prep_fixtures import dnerf_clip, tree  # noqa: E402
from _trainer_toy import run_two_ranks  # noqa: E402

from data_prep.cli import main  # noqa: E402
from data_prep.converters import convert_each  # noqa: E402
from data_prep.curate import CurationConfig, curate  # noqa: E402
from data_prep.engine import Engine  # noqa: E402
from training.stage_config import StageConfig  # noqa: E402
from training.trainer import TrainerConfig  # noqa: E402

pytestmark = pytest.mark.slow

SIZE, FRAMES = 32, 9
RAY = Engine("ray")  # joins the Ray this module started
THRESHOLDS = CurationConfig(min_frames=FRAMES, min_translation_m=0.0, min_sharpness=5000.0, min_valid_depth_ratio=0.0)


@pytest.fixture(scope="module")
def local_ray():
    """A local Ray of 2 CPUs, started by this module and shut down after it."""
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, logging_level="ERROR")
    yield
    ray.shutdown()


@pytest.fixture(scope="module")
def synth_pair(local_ray, tmp_path_factory):
    """``data_prep synth`` of the same 6 scenes on each engine (the ray one through the command line)."""
    root = tmp_path_factory.mktemp("synth")
    common = ["synth", "--scenes", "6", "--seed", "9", "--size", str(SIZE), "--frames", str(FRAMES),
              "--cameras", "2", "--static-ratio", "0.5", "--quiet"]
    assert main([*common, "--out", str(root / "local"), "--engine", "local", "--workers", "1"]) == 0
    assert main([*common, "--out", str(root / "ray"), "--engine", "ray"]) == 0
    return root / "local", root / "ray"


def test_synth_on_ray_is_the_local_dataset_byte_for_byte(synth_pair):
    local, on_ray = synth_pair
    a, b = tree(local), tree(on_ray)
    assert len([k for k in a if k.endswith("meta.json")]) == 6
    assert a.keys() == b.keys() and all(a[k] == b[k] for k in a)


def test_convert_each_on_ray_is_the_local_dataset_byte_for_byte(local_ray, tmp_path):
    src = tmp_path / "dnerf"
    for name, times in (("lego", (0.0, 0.5, 1.0)), ("mutant", (0.0, 1.0)), ("jumpingjacks", (1.0, 0.0, 0.5, 0.25))):
        dnerf_clip(src / name, times=times)
    outs = {}
    for engine in (Engine("local", workers=1), RAY):
        outs[engine.name] = convert_each("dnerf", src, tmp_path / engine.name, engine=engine, progress=False)
    assert [p.name for p in outs["ray"]] == ["jumpingjacks", "lego", "mutant"]
    a, b = tree(tmp_path / "local"), tree(tmp_path / "ray")
    assert len([k for k in a if k.endswith("meta.json")]) == 3
    assert a.keys() == b.keys() and all(a[k] == b[k] for k in a)


def test_convert_each_names_the_failing_clip_from_a_ray_task(local_ray, tmp_path):
    src = tmp_path / "dnerf"
    dnerf_clip(src / "good", times=(0.0, 1.0))
    (src / "broken").mkdir()  # no transforms file
    with pytest.raises(FileNotFoundError, match="^dnerf clip broken: "):
        convert_each("dnerf", src, tmp_path / "out", engine=RAY, progress=False)
    assert (tmp_path / "out" / "good" / "meta.json").is_file() or not (tmp_path / "out" / "good").exists()
    assert not (tmp_path / "out" / "broken").exists()


@pytest.fixture(scope="module")
def curated_pair(synth_pair, tmp_path_factory):
    """``curate`` of the local synth dataset on each engine, with thresholds that accept some scenes."""
    local, _ = synth_pair
    root = tmp_path_factory.mktemp("curated")
    curate(local, root / "local", THRESHOLDS, workers=1, progress=False)
    curate(local, root / "ray", THRESHOLDS, engine=RAY, progress=False)
    return root / "local", root / "ray"


def test_curate_on_ray_is_the_local_curation_byte_for_byte(curated_pair):
    local, on_ray = curated_pair
    a, b = tree(local), tree(on_ray)
    accepted = (local / "accepted.txt").read_text().split()
    assert 2 <= len(accepted) < 6  # some accepted (as symlinks), some rejected
    assert all(a[name].startswith("-> ") for name in accepted)
    assert a.keys() == b.keys() and all(a[k] == b[k] for k in a)


def test_two_ranks_train_on_a_ray_curated_dataset(curated_pair, tmp_path):
    """``torchrun --nproc_per_node 2 -m training.train`` (two gloo ranks) on the Ray curation's output folder: the
    ranks form a group of two, read the accepted scenes only, and the run finishes."""
    _, on_ray = curated_pair
    accepted = sorted((on_ray / "accepted.txt").read_text().split())
    trainer = TrainerConfig(run_dir=str(tmp_path / "run"), total_steps=2, batch_size=1, lr=1e-3, warmup_steps=1,
                            checkpoint_every=100, progress=False, seed=0)
    stage = StageConfig(name="stage1", model_config="tiny", init_from=None, data=str(on_ray), height=SIZE,
                        width=SIZE, num_frames=FRAMES, render_frames=2, trainer=trainer, train=("ldrm",),
                        objectives=("reconstruction",), scenes="all")
    cfg = tmp_path / "stage.yaml"
    cfg.write_text(yaml.safe_dump(json.loads(json.dumps(dataclasses.asdict(stage)))))
    script = textwrap.dedent(f"""
        import json, os, sys
        import training.train as train
        built = []
        real = train.build_training
        train.build_training = lambda stage, seed=None: built.append(real(stage, seed)) or built[-1]
        code = train.main(["--config", {str(cfg)!r}, "--strategy", "ddp", "--device", "cpu", "--quiet"])
        trainer = built[0][0]
        with open({str(tmp_path)!r} + f"/rank{{os.environ['RANK']}}.json", "w") as f:
            json.dump({{"scenes": sorted({{it.scene for it in trainer.dataset.items}}), "world": trainer.world}}, f)
        sys.exit(code)
    """)
    run_two_ranks(script, timeout=300, fresh=(tmp_path / "run",))
    ranks = [json.loads((tmp_path / f"rank{r}.json").read_text()) for r in range(2)]
    assert all(r["scenes"] == accepted and r["world"] == 2 for r in ranks)
    assert (tmp_path / "run" / "metrics.csv").is_file()
