"""Config overrides (``{"section.field": value}``) used by the bench and the job runner."""

import pytest

from nepf_core.config import fast
from nepf_core.jobs import build_config


def test_bool_overrides_parse_false_as_false():
    assert fast().render.unlit_albedo_stopgrad is True
    base = fast()
    assert base.render.unlit_albedo_stopgrad is True and base.render.surface_refine is True
    cfg = build_config("fast", None, {"render.unlit_albedo_stopgrad": "False",
                                      "render.surface_refine": "0", "render.specular": "false"})
    assert cfg.render.unlit_albedo_stopgrad is False
    assert cfg.render.surface_refine is False
    assert cfg.render.specular is False


def test_numeric_overrides_and_iters():
    assert fast().model.init_variance != 0.25
    cfg = build_config("fast", 7, {"model.init_variance": "0.25", "train.batch_rays": "256"})
    assert cfg.model.init_variance == 0.25 and cfg.train.batch_rays == 256 and cfg.train.iters == 7


@pytest.mark.parametrize("ov,msg", [({"render.specular": "maybe"}, "is a bool"),
                                    ({"render.nope": "1"}, "unknown config field"),
                                    ({"nope.x": "1"}, "unknown config field"),
                                    ({"model.photon.nope": "1"}, "unknown config field"),
                                    ({"model.name.x": "1"}, "unknown config field"),
                                    ({"train": "1"}, "unknown config field")])
def test_bad_overrides_name_the_field(ov, msg):
    with pytest.raises(ValueError, match=msg):
        build_config("fast", None, ov)


def test_nested_overrides_reach_head_configs_without_touching_the_others():
    base = fast()
    cfg = build_config("fast", None, {"model.photon.use_feature": "true", "model.photon.n_freqs_x": "6"})
    assert cfg.model.photon.use_feature is True and cfg.model.photon.n_freqs_x == 6
    assert base.model.photon.use_feature is False and base.model.photon.n_freqs_x != 6
    assert cfg.model.material == base.model.material and cfg.model.radiance == base.model.radiance
