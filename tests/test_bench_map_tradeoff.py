"""The map trade-off benchmark's configuration variants: each changes exactly one key of the shipped
configs/companion.toml, in the right table, and still loads (DESIGN §7)."""

import difflib
import tomllib

import pytest

from bench import map_tradeoff as M
from companion.io.config_files import load_companion_config


def test_each_variant_changes_one_key_in_its_table(tmp_path):
    base = M.BASE_CONFIG.read_text(encoding="utf-8")
    shipped = tomllib.loads(base)
    for name, change in M.VARIANTS.items():
        text = M.variant_text(base, change)
        diff = [l for l in difflib.unified_diff(base.splitlines(), text.splitlines(), lineterm="", n=0)
                if l[:1] in "+-" and not l.startswith(("+++", "---"))]
        data = tomllib.loads(text)
        if change is None:
            assert diff == [] and data == shipped
            continue
        table, key, value = change
        assert len(diff) == 2, name
        assert data[table][key] == pytest.approx(float(value))
        assert shipped[table][key] != data[table][key]
        assert {t: {k: v for k, v in d.items() if k != key} for t, d in data.items() if isinstance(d, dict)} == \
               {t: {k: v for k, v in d.items() if k != key} for t, d in shipped.items() if isinstance(d, dict)}
        path = tmp_path / "c.toml"
        path.write_text(text, encoding="utf-8")
        cfg = load_companion_config(path)
        assert getattr(getattr(cfg, table), key) == pytest.approx(float(value))


def test_a_missing_key_is_an_error():
    with pytest.raises(KeyError, match="no_such_key"):
        M.variant_text(M.BASE_CONFIG.read_text(encoding="utf-8"), ("map", "no_such_key", "1"))
