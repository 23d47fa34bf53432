"""The YAML reader every file loader uses: safe types, no aliases, a size bound."""

from __future__ import annotations

import pytest
import yaml

from mmpa.core.errors import ConfigError
from mmpa.core.yamlio import load_yaml, load_yaml_text

BOMB = "\n".join(
    ["a: &a [x, x, x, x, x, x, x, x, x, x]"]
    + [
        f"{chr(98 + i)}: &{chr(98 + i)} [" + ", ".join([f"*{chr(97 + i)}"] * 10) + "]"
        for i in range(8)
    ]
)


def test_plain_documents_parse_like_safe_load() -> None:
    text = "name: t\nvalues: [1, 2.5, null]\nnested: {a: true, b: 'x'}\nanchor: &k 3\n"
    assert load_yaml_text(text) == yaml.safe_load(text)


def test_alias_bomb_refused_before_expansion() -> None:
    with pytest.raises(ConfigError, match=r"alias \*a is not accepted"):
        load_yaml_text(BOMB, "bomb.yaml")


def test_python_tags_refused() -> None:
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_yaml_text("x: !!python/object/apply:os.system ['true']")


def test_size_bound_and_file_errors_name_the_file(tmp_path) -> None:
    big = tmp_path / "big.yaml"
    big.write_text("x: " + "a" * 2000)
    with pytest.raises(ConfigError, match=r"big\.yaml: 2003 bytes"):
        load_yaml(big, max_bytes=1000)
    assert load_yaml(big)["x"] == "a" * 2000
    with pytest.raises(ConfigError, match=r"cannot read .*missing\.yaml"):
        load_yaml(tmp_path / "missing.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_bytes(b"x: \xff\xfe")
    with pytest.raises(ConfigError, match=r"bad\.yaml: not UTF-8"):
        load_yaml(bad)
