"""The benches' shared model flags: a built model gets the asked decoder; a model file without an atlas is refused."""
import argparse
import dataclasses

import pytest

from tools.bench.render import add_model_args, model_from_args


def _args(argv):
    ap = argparse.ArgumentParser()
    add_model_args(ap, 3, "model")
    return ap.parse_args(argv)


def test_built_model_has_the_asked_decoder_and_says_so():
    args = _args(["--points", "200", "--atlas-steps", "1"])
    assert args.model is None and args.atlas_steps == 1
    bundle, source = model_from_args(args, decoder="unet")
    assert bundle.model.cfg.decoder == "unet" and bundle.model.num_points == 200 and bundle.atlas is not None
    assert "200 points" in source and "unet" in source


def test_model_file_without_atlas_is_refused_by_name(tmp_path):
    from core.bundle import save_bundle

    bundle, _ = model_from_args(_args(["--points", "150", "--atlas-steps", "1"]))
    path = tmp_path / "no_atlas.pgt"
    save_bundle(str(path), dataclasses.replace(bundle, atlas=None))
    with pytest.raises(SystemExit, match="no_atlas.pgt: this model has no atlas"):
        model_from_args(_args(["--model", str(path)]))
