"""Tests of como3r/prior/mast3r/config.py: parsing the constructor string without eval."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from como3r.errors import CheckpointError, ConfigError
from como3r.prior.mast3r.config import RELEASED_MODEL_STRING, MASt3RConfig, parse_model_string


def test_released_string_gives_released_configuration():
    config = parse_model_string(RELEASED_MODEL_STRING)
    assert config == MASt3RConfig()
    assert (config.enc_embed_dim, config.enc_depth, config.enc_num_heads) == (1024, 24, 16)
    assert (config.dec_embed_dim, config.dec_depth, config.dec_num_heads) == (768, 12, 12)
    assert config.rope_base == 100.0 and config.desc_dim == 24 and config.two_confs
    assert (config.conf_min, config.conf_max) == (1.0, math.inf)
    assert (config.desc_conf_min, config.desc_conf_max) == (0.0, math.inf)
    assert config.dpt_hooks == (0, 6, 9, 12)
    assert config.local_channels == 25


def test_argument_order_and_inf_spellings_do_not_matter():
    text = (
        "AsymmetricMASt3R(two_confs=True, dec_num_heads=12, dec_depth=12, dec_embed_dim=768,"
        " enc_num_heads=16, enc_depth=24, enc_embed_dim=1024,"
        " desc_conf_mode=('exp', 0, float('inf')), conf_mode=('exp', 1, float('inf')),"
        " depth_mode=('exp', float('-inf'), inf), output_mode='pts3d+desc24',"
        " head_type='catmlp+dpt', img_size=(512, 512), patch_embed_cls='PatchEmbedDust3R',"
        " pos_embed='RoPE100', landscape_only=True)"
    )
    assert parse_model_string(text) == MASt3RConfig()


def test_class_defaults_apply_to_omitted_optional_arguments(tiny_model_string):
    text = tiny_model_string.replace(", two_confs=True", "").replace(
        ", desc_conf_mode=('exp', 0, inf)", ""
    )
    config = parse_model_string(text)
    assert not config.two_confs
    assert config.local_channels == config.desc_dim
    # desc_conf_mode falls back to conf_mode (spec §5.4)
    assert (config.desc_conf_min, config.desc_conf_max) == (config.conf_min, config.conf_max)


def test_rope_base_and_descriptor_dim_are_parsed(tiny_model_string):
    text = tiny_model_string.replace("RoPE100", "RoPE50.5").replace("desc24", "desc16")
    config = parse_model_string(text)
    assert config.rope_base == 50.5 and config.desc_dim == 16


@pytest.mark.parametrize(
    ("change", "named"),
    [
        (("two_confs=True", "two_confs=True, bogus_arg=3"), "bogus_arg"),
        (("enc_depth=2, ", ""), "enc_depth"),
        (("RoPE100", "cosine"), "pos_embed"),
        (("catmlp+dpt", "dpt"), "head_type"),
        (("pts3d+desc24", "pts3d"), "output_mode"),
        (("conf_mode=('exp', 1, inf)", "conf_mode=('sqrt', 1, inf)"), "conf_mode"),
        (("depth_mode=('exp', -inf, inf)", "depth_mode=('exp', 0, 10)"), "depth_mode"),
        (("enc_depth=2", "enc_depth=2.5"), "enc_depth"),
        (("two_confs=True", "two_confs=1"), "two_confs"),
        (("two_confs=True", "two_confs=True, patch_size=8"), "patch_size"),
        (("enc_num_heads=2", "enc_num_heads=3"), "enc_embed_dim"),
        (("ManyAR_PatchEmbed", "PatchEmbed"), "patch_embed_cls"),
    ],
)
def test_bad_arguments_are_named(tiny_model_string, change, named):
    text = tiny_model_string.replace(*change)
    assert text != tiny_model_string
    with pytest.raises(CheckpointError, match=named):
        parse_model_string(text)


@pytest.mark.parametrize(
    "text",
    [
        "AsymmetricCroCo3DStereo(enc_embed_dim=32)",
        "AsymmetricMASt3R(32, enc_depth=2)",
        "AsymmetricMASt3R(**kwargs)",
        "AsymmetricMASt3R(enc_embed_dim=32",
        "models.AsymmetricMASt3R(enc_embed_dim=32)",
        "[AsymmetricMASt3R(enc_embed_dim=32)]",
    ],
)
def test_malformed_strings_are_refused(text):
    with pytest.raises(CheckpointError):
        parse_model_string(text)


def test_code_in_a_string_is_never_run(tiny_model_string, tmp_path: Path):
    marker = tmp_path / "ran"
    payload = f"__import__('os').system('touch {marker}')"
    text = tiny_model_string.replace("enc_depth=2", f"enc_depth={payload}")
    with pytest.raises(CheckpointError, match="not a literal"):
        parse_model_string(text)
    assert not marker.exists()


def test_direct_construction_is_validated():
    with pytest.raises(ConfigError, match="enc_depth"):
        MASt3RConfig(enc_depth=0)
    with pytest.raises(ConfigError, match="multiple of 4"):
        MASt3RConfig(dec_embed_dim=36, dec_num_heads=6)
