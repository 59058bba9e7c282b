"""NeRF-SH configuration: presets, JSON round trip, validation, --help from field docstrings."""

from __future__ import annotations

import dataclasses

import pytest

from plenoctree.errors import ConfigError
from plenoctree.nerf.config import (ModelConfig, TrainConfig, config_from_dict, config_to_dict,
                                    field_docs, preset, validate)


def test_paper_preset_is_the_paper():
    cfg = preset("paper")
    m = cfg.model
    assert (m.encoding, m.pe_freqs, m.net_depth, m.net_width, m.skip_layer) == \
        ("posenc", 10, 8, 256, 4)
    assert (m.basis, m.sh_degree, m.sigma_activation, m.coarse) == ("sh", 3, "relu", True)
    assert (cfg.sampler, cfg.n_coarse, cfg.n_fine, cfg.batch_rays) == \
        ("hierarchical", 64, 128, 1024)
    assert (cfg.lr_init, cfg.lr_final, cfg.max_steps) == (5e-4, 5e-6, 2_000_000)
    assert (cfg.sparsity_weight, cfg.sparsity_length, cfg.sparsity_points) == (1e-3, 0.05, 10000)
    assert cfg.amp == "off"
    # the dataclass defaults carry the paper's sparsity prior too
    d = TrainConfig()
    assert (d.sparsity_weight, d.sparsity_length, d.sparsity_points) == (1e-3, 0.05, 10000)


def test_cpu_preset():
    cfg = preset("cpu")
    assert cfg.sampler == "occupancy" and cfg.model.encoding == "hashgrid"
    assert cfg.model.basis == "sh" and cfg.model.sh_degree == 3 and not cfg.model.coarse
    validate(cfg)
    with pytest.raises(ConfigError):
        preset("tpu")


def test_gpu_preset_takes_fixed_shape_steps():
    cfg = preset("gpu")
    validate(cfg)
    assert cfg.fixed_step and cfg.target_samples == 1 << 18 and cfg.max_steps == 20000
    assert cfg.model.grid_log2_table == 19 and cfg.sampler == "occupancy"
    cfg.sampler = "hierarchical"
    with pytest.raises(ConfigError, match="fixed_step"):
        validate(cfg)


def test_round_trip_and_unknown_keys():
    cfg = preset("paper")
    cfg.background = (0.0, 0.5, 1.0)
    d = config_to_dict(cfg)
    back = config_from_dict(d)
    assert back == cfg
    d["bogus"] = 1
    with pytest.raises(ConfigError, match="bogus"):
        config_from_dict(d)
    d = config_to_dict(cfg)
    d["model"]["nope"] = 2
    with pytest.raises(ConfigError, match="nope"):
        config_from_dict(d)


@pytest.mark.parametrize("change", [
    dict(sampler="magic"), dict(amp="fp8"), dict(render_step=0.0), dict(downscale=0),
    dict(threads=-2), dict(model=ModelConfig(basis="rgb")), dict(model=ModelConfig(sh_degree=5)),
    dict(model=ModelConfig(coarse=True)),       # a coarse net with the occupancy sampler
])
def test_validation(change):
    cfg = dataclasses.replace(preset("cpu"), **change)
    with pytest.raises(ConfigError):
        validate(cfg)


def test_every_field_has_help():
    for cls in (TrainConfig, ModelConfig):
        docs = field_docs(cls)
        missing = [f.name for f in dataclasses.fields(cls) if not docs.get(f.name)]
        assert not missing, (cls.__name__, missing)


def test_cli_help_and_print_config(capsys):
    from plenoctree.cli import main

    with pytest.raises(SystemExit):
        main(["train", "--help"])
    text = capsys.readouterr().out
    assert "--sparsity-weight" in text and "--sh-degree" in text and "--steps" in text
    assert "Position encoding" in text                     # a field docstring
    assert main(["train", "--out", "x", "--preset", "paper", "--steps", "7", "--basis", "sg",
                 "--batch-size", "64", "--print-config"]) == 0
    out = capsys.readouterr().out
    import json

    cfg = json.loads(out)
    assert cfg["max_steps"] == 7 and cfg["model"]["basis"] == "sg" and cfg["batch_rays"] == 64
    assert cfg["model"]["net_width"] == 256
