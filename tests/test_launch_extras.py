"""Replacing a section of the YAML from the command line: a `*_type` switched to another type
drops the keys of the YAML's old type, `section=null` clears a section, and a key the type does
not take fails naming the key and both fixes."""
import logging

import pytest

from trial_helpers import ROOT
from gs_regional.config import ConfigError, load_config, parse_structured
from gs_regional.launch import load_plugins, main
from gs_regional.launch.sections import section_configs
from gs_regional.registry import find, load_builtins

EDIT = str(ROOT / "configs" / "edit.yaml")
DROPPED = "dtype, guidance_scale, image_guidance_scale, num_inference_steps, pretrained"


@pytest.fixture(scope="module", autouse=True)
def plugins():
    load_builtins()
    assert load_plugins(ROOT / "custom").get("custom/example_plugin.py", "missing") is None


def read(*overrides):
    return load_config(EDIT, list(overrides), section_configs=section_configs)


def test_switching_the_guidance_type_drops_the_old_types_keys(caplog):
    with caplog.at_level(logging.INFO, logger="gs_regional.config"):
        cfg = read("system.guidance_type=grayscale-editor", "system.guidance.strength=0.5")
    # The key both types take (batch_size) stays, the command line's key is kept.
    assert dict(cfg.system.guidance) == {"batch_size": "auto", "strength": 0.5}
    editor = find("grayscale-editor", kind="guidance")(cfg.system.guidance)
    assert editor.cfg.strength == 0.5
    (note,) = [r.getMessage() for r in caplog.records if r.name == "gs_regional.config"]
    assert note == ("system.guidance_type=grayscale-editor replaces the YAML's instructpix2pix: the YAML's "
                    f"system.guidance keys that grayscale-editor does not take are dropped: {DROPPED}")
    # Nothing else of the YAML moved.
    assert cfg.system.depth.pretrained == "depth-anything/Depth-Anything-V2-Small-hf"
    assert read().system.guidance.pretrained == "timbrooks/instruct-pix2pix"  # no switch: all kept


def test_a_key_the_new_type_does_not_take_fails_naming_it_and_the_fixes():
    with pytest.raises(ConfigError) as e:
        read("system.guidance_type=grayscale-editor", "system.guidance.strenght=0.5")
    msg = str(e.value)
    assert "unknown config key 'system.guidance.strenght' (did you mean 'strength'?)" in msg
    assert "for system.guidance_type=grayscale-editor; allowed keys: batch_size, luma, strength" in msg
    assert "Correct or remove the key" in msg and "give system.guidance=null" in msg
    # The same for a misspelt key of the YAML's own type, named by its config path.
    with pytest.raises(ConfigError, match=r"unknown config key 'system\.guidance\.pretrainedd' \(did you mean "
                                          r"'pretrained'\?\) for system\.guidance_type=instructpix2pix.*guidance=null"):
        read("system.guidance.pretrainedd=x")


def test_null_clears_a_section_and_an_empty_mapping_says_so():
    cfg = read("system.guidance=null")
    assert dict(cfg.system.guidance) == {}  # the guidance's defaults apply
    cfg = read("system.guidance=null", "system.guidance.num_inference_steps=5")
    assert dict(cfg.system.guidance) == {"num_inference_steps": 5}  # keys given after it are kept
    cfg = read("system.guidance_type=grayscale-editor", "system.guidance=null")
    assert dict(cfg.system.guidance) == {}
    parse_structured(find("grayscale-editor").Config, cfg.system.guidance, where="system.guidance")
    with pytest.raises(ConfigError, match=r"override 'system\.guidance=\{\}' changes nothing.*system\.guidance=null"):
        read("system.guidance={}")
    assert read("resume=null").resume is None  # null is still a value where the YAML has no section


def test_switching_other_types():
    cfg = read("system_type=in2n")
    assert "localization" not in cfg.system and "refine" not in cfg.system  # regional-edit's own keys
    assert cfg.system.guidance.pretrained == "timbrooks/instruct-pix2pix"  # in2n takes these too
    cfg = read("system.renderer_type=auto", "system.renderer.strip_width=8")  # auto: either candidate's keys
    assert cfg.system.renderer.strip_width == 8
    with pytest.raises(Exception, match="system.guidance_type: unknown guidance type 'no-such-editor'"):
        read("system.guidance_type=no-such-editor")


def test_launch_reports_an_unknown_key_of_a_switched_type_in_one_line(tmp_path, capsys):
    argv = ["--config", EDIT, "--train", f"exp_root_dir={tmp_path}", "system.guidance_type=grayscale-editor",
            "system.guidance.strenght=0.5"]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    last = err.strip().splitlines()[-1]
    assert last.startswith("error: ") and "'system.guidance.strenght'" in last and "system.guidance=null" in last
    assert not any(tmp_path.iterdir())


def test_a_moved_key_of_a_type_section_says_where_it_went(tmp_path):
    from dataclasses import dataclass
    from typing import ClassVar, Dict

    @dataclass
    class Config:
        MOVED_KEYS: ClassVar[Dict[str, str]] = {"old": "system.thing.new"}
        new: int = 0

    path = tmp_path / "c.yaml"
    path.write_text("system:\n  thing_type: t\n  thing:\n    old: 1\n")
    with pytest.raises(ConfigError, match=r"config key 'system\.thing\.old' has moved: use 'system\.thing\.new'"):
        load_config(str(path), [], section_configs=lambda key, name: [Config] if key == "system.thing_type" else None)
    cfg = load_config(str(path), ["system.thing_type=u"], section_configs=lambda key, name: [Config])
    assert dict(cfg.system.thing) == {}  # the switch dropped the key the new type does not take
