"""Per-stage code hashes: follow imports, ignore comments and docstrings."""

from __future__ import annotations

import shutil
import sys
import textwrap

import pytest

from omnilidar import provenance


@pytest.fixture()
def package_copy(tmp_path, monkeypatch):
    """A throwaway package laid out like omnilidar, hashed by a patched provenance."""
    pkg = tmp_path / "omnilidar"
    (pkg / "commands").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "commands" / "__init__.py").write_text("")
    (pkg / "core.py").write_text("def f():\n    return 1\n")
    (pkg / "other.py").write_text("def g():\n    return 2\n")
    (pkg / "helpers.py").write_text("X = 3\n")
    (pkg / "commands" / "stage.py").write_text(textwrap.dedent('''\
        """A stage."""
        from omnilidar.core import f


        def run():
            from .. import helpers  # a relative import inside a function
            return f() + helpers.X
        '''))
    monkeypatch.setattr(provenance, "PACKAGE_DIR", pkg)
    provenance._parsed.cache_clear()
    yield pkg
    provenance._parsed.cache_clear()


def _hash():
    provenance._parsed.cache_clear()
    return provenance.command_code_hash("stage")


def test_closure_follows_absolute_relative_and_local_imports(package_copy):
    files = {p.name for p in provenance.module_closure("omnilidar.commands.stage")}
    assert files == {"stage.py", "core.py", "helpers.py", "__init__.py"}
    assert "other.py" not in files


def test_comment_docstring_and_formatting_edits_keep_the_hash(package_copy):
    before = _hash()
    core = package_copy / "core.py"
    core.write_text('"""Docstring added."""\n# a comment\n\ndef f():\n    """Doc."""\n    return   1  # why\n')
    assert _hash() == before


def test_code_edits_in_an_imported_module_change_the_hash(package_copy):
    before = _hash()
    (package_copy / "helpers.py").write_text("X = 4\n")
    assert _hash() != before


def test_edits_in_unrelated_modules_keep_the_hash(package_copy):
    before = _hash()
    (package_copy / "other.py").write_text("def g():\n    return 99\n")
    assert _hash() == before


def test_real_commands_hash_and_unknown_module_fails():
    assert len(provenance.command_code_hash("index-dataset")) == 16
    with pytest.raises(ValueError, match="no such package module"):
        provenance.code_hash("omnilidar.does_not_exist")


def test_config_hash_ignores_key_order_but_not_values():
    assert provenance.config_hash({"a": 1, "b": 2}) == provenance.config_hash({"b": 2, "a": 1})
    assert provenance.config_hash({"a": 1, "b": 2}) != provenance.config_hash({"a": 2, "b": 1})


def test_excluded_modules_are_neither_hashed_nor_followed(package_copy):
    files = {p.name for p in provenance.module_closure("omnilidar.commands.stage", exclude=("omnilidar.core",))}
    assert "core.py" not in files and "helpers.py" in files
    before = provenance.command_code_hash("stage", exclude=("omnilidar.core",))
    (package_copy / "core.py").write_text("def f():\n    return 5\n")
    provenance._parsed.cache_clear()
    assert provenance.command_code_hash("stage", exclude=("omnilidar.core",)) == before
