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
    (pkg / "cli.py").write_text("import importlib\nfrom omnilidar import commands\n")
    (pkg / "commands" / "another.py").write_text("Y = 1\n")
    (pkg / "commands" / "stage.py").write_text(textwrap.dedent('''\
        """A stage."""
        from omnilidar.core import f


        def run():
            from .. import helpers  # a relative import inside a function
            return f() + helpers.X
        '''))
    monkeypatch.setattr(provenance, "PACKAGE_DIR", pkg)
    provenance.clear_caches()
    yield pkg
    provenance.clear_caches()


def _hash():
    provenance.clear_caches()
    return provenance.command_code_hash("stage")


def test_closure_follows_absolute_relative_and_local_imports(package_copy):
    files = {p.name for p in provenance.module_closure("omnilidar.commands.stage")}
    assert files == {"stage.py", "core.py", "helpers.py", "__init__.py"}
    assert "other.py" not in files


def test_a_command_hash_covers_the_entry_point_but_not_the_other_commands(package_copy):
    before = _hash()
    (package_copy / "commands" / "another.py").write_text("Y = 2\n")
    assert _hash() == before
    (package_copy / "cli.py").write_text("import importlib\nfrom omnilidar import commands\nZ = 1\n")
    assert _hash() != before


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


def _plugin_package(pkg):
    """A registry (DISPATCHES) of three plugins, one of which imports another."""
    (pkg / "plugins").mkdir()
    (pkg / "plugins" / "__init__.py").write_text("")
    (pkg / "plugins" / "used.py").write_text("from omnilidar.plugins.shared import S\nU = S + 1\n")
    (pkg / "plugins" / "shared.py").write_text("S = 1\n")
    (pkg / "plugins" / "unused.py").write_text("V = 1\n")
    (pkg / "registry.py").write_text(textwrap.dedent('''\
        from omnilidar.plugins import shared, unused, used

        DISPATCHES = ("omnilidar.plugins",)
        PLUGINS = {"shared": shared, "unused": unused, "used": used}
        '''))
    (pkg / "commands" / "stage.py").write_text("from omnilidar.registry import PLUGINS\n")


def test_exclude_cuts_the_registry_import_but_not_imports_by_used_modules(package_copy):
    _plugin_package(package_copy)
    exclude = ("omnilidar.plugins.shared", "omnilidar.plugins.unused")
    files = {p.name for p in provenance.module_closure("omnilidar.commands.stage", exclude=exclude)}
    assert {"registry.py", "used.py", "shared.py"} <= files and "unused.py" not in files

    def stage_hash():
        provenance.clear_caches()
        return provenance.command_code_hash("stage", exclude=exclude)

    before = stage_hash()
    (package_copy / "plugins" / "unused.py").write_text("V = 2\n")
    assert stage_hash() == before, "a plugin the stage does not use"
    (package_copy / "plugins" / "shared.py").write_text("S = 2\n")
    assert stage_hash() != before, "excluded from the registry, but imported by a used plugin"
    assert "unused.py" in {p.name for p in provenance.module_closure("omnilidar.commands.stage")}


def test_exclude_of_a_module_no_registry_dispatches_to_fails(package_copy):
    with pytest.raises(ValueError, match="registry imports"):
        provenance.command_code_hash("stage", exclude=("omnilidar.core",))
    with pytest.raises(ValueError, match="no such package module"):
        provenance.command_code_hash("stage", exclude=("omnilidar.nothing",))


def _declare(pkg, *files):
    (pkg / "helpers.py").write_text(f"DATA_FILES = {files!r}\nX = 3\n")


def test_declared_data_files_are_hashed_up_to_comments_and_formatting(package_copy):
    root = package_copy.parent
    (root / "tables").mkdir()
    (root / "tables" / "t.yaml").write_text("# a table\na: 1\nb:\n  - 2\ntext: |\n  # kept: block content\n")
    (root / "tables" / "t.json").write_text('{"a": 1, "b": [2]}')
    (root / "tables" / "t.txt").write_text("x\n")
    _declare(package_copy, "tables/t.yaml", "tables/t.json", "tables/t.txt")
    before = _hash()
    (root / "tables" / "t.yaml").write_text("a: 1   \n\n# another comment\nb:\n  - 2\ntext: |\n  # kept: block content\n")
    (root / "tables" / "t.json").write_text('{\n  "b": [2],\n  "a": 1\n}\n')
    assert _hash() == before
    for name, content in (("t.yaml", "a: 1\nb:\n  - 3\ntext: |\n  # kept: block content\n"),
                          ("t.yaml", "a: 1\nb:\n  - 2\ntext: |\n  # edited block content\n"),
                          ("t.json", '{"a": 1, "b": [3]}'), ("t.txt", "y\n")):
        old = (root / "tables" / name).read_text()
        (root / "tables" / name).write_text(content)
        assert _hash() != before, (name, content)
        (root / "tables" / name).write_text(old)
    assert _hash() == before


def test_a_declared_data_file_that_does_not_exist_fails(package_copy):
    _declare(package_copy, "tables/missing.yaml")
    with pytest.raises(ValueError, match="DATA_FILES names 'tables/missing.yaml'"):
        _hash()


@pytest.fixture()
def project_copy(tmp_path, monkeypatch, project_root):
    """A copy of the real package and its schemas, hashed by a patched provenance."""
    shutil.copytree(project_root / "omnilidar", tmp_path / "omnilidar",
                    ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copytree(project_root / "workflow" / "schemas", tmp_path / "workflow" / "schemas")
    monkeypatch.setattr(provenance, "PACKAGE_DIR", tmp_path / "omnilidar")
    provenance.clear_caches()
    yield tmp_path
    provenance.clear_caches()


EFFECTS = ("beam_missing", "beam_reduction", "fog", "rain", "snow", "wet_ground")


def _domain_hash(*used):
    """build-domain's hash for a domain applying ``used`` (as rules/common.smk's domain_code)."""
    provenance.clear_caches()
    unused = tuple(f"omnilidar.domains.effects.{m}" for m in EFFECTS if m not in used)
    return provenance.command_code_hash("build-domain", exclude=unused)


def _edit(path):
    path.write_text(path.read_text() + "\n_EDITED = True\n")


def test_a_domain_depends_on_its_effects_and_what_they_import_only(project_copy):
    effects = project_copy / "omnilidar" / "domains" / "effects"
    fog, beam_missing, vehicle = _domain_hash("fog"), _domain_hash("beam_missing"), _domain_hash()
    _edit(effects / "snow.py")
    assert (_domain_hash("fog"), _domain_hash("beam_missing"), _domain_hash()) == (fog, beam_missing, vehicle)
    _edit(effects / "beam_reduction.py")
    assert _domain_hash("beam_missing") != beam_missing, "beam_missing imports beam_reduction"
    assert _domain_hash("fog") == fog
    _edit(effects / "fog.py")
    assert _domain_hash("fog") != fog


def _command_hashes(*commands):
    provenance.clear_caches()
    return [provenance.command_code_hash(c) for c in commands]


def test_editing_bev_metrics_reruns_no_labelling_or_segmentation(project_copy):
    stages = ("pseudo-label", "train-labeler", "train-segmentor", "evaluate-segmentor", "generation-quality")
    before = _command_hashes(*stages)
    _edit(project_copy / "omnilidar" / "metrics" / "bev.py")
    after = _command_hashes(*stages)
    assert after[:4] == before[:4]
    assert after[4] != before[4], "generation quality does use the BEV metrics"


def test_a_schema_edit_reruns_the_stages_that_read_it(project_copy):
    stages = ("train-generator", "sample", "build-domain", "train-segmentor")
    before = _command_hashes(*stages)
    schema = project_copy / "workflow" / "schemas" / "generator.schema.yaml"
    text = schema.read_text()
    schema.write_text("# a comment\n" + text.replace("\n", "\n\n", 3))
    assert _command_hashes(*stages) == before, "comments and blank lines"
    assert "\npresets:" in text
    schema.write_text(text.replace("\npresets:", "\npresets:\n  extra_preset: {}", 1))
    after = _command_hashes(*stages)
    assert after[0] != before[0] and after[1] != before[1], "train-generator reads the presets"
    assert after[2:] == before[2:]


def test_schema_descriptions_rerun_nothing_but_defaults_do(tmp_path):
    """A schema's prose (description, title) changes no validation or default: no hash changes."""
    from omnilidar.provenance import _data_content

    schema = tmp_path / "s.schema.yaml"
    schema.write_text("type: object\nproperties:\n  lr:\n    type: number\n    default: 0.1\n"
                      "    description: Learning rate.\n")
    before = _data_content(schema)
    schema.write_text("type: object\ntitle: Now titled\nproperties:\n  lr:\n    type: number\n    default: 0.1\n"
                      "    description: >\n      The learning rate, explained at length.\n")
    assert _data_content(schema) == before
    schema.write_text(schema.read_text().replace("default: 0.1", "default: 0.2"))
    assert _data_content(schema) != before


def test_parsed_module_facts_are_cached_by_content_and_a_damaged_entry_is_recomputed(package_copy, tmp_path,
                                                                                     monkeypatch):
    monkeypatch.setenv("OMNILIDAR_CACHE_DIR", str(tmp_path / "cache"))
    first = _hash()
    entries = sorted(provenance._facts_cache_dir().glob("*.json"))
    closure = provenance.module_closure(*provenance.command_modules("stage"))
    assert len(entries) == len({f.read_text() for f in closure})  # one entry per distinct source
    assert _hash() == first  # read back from the cache
    for entry in entries:
        entry.write_text("{not json")
    assert _hash() == first  # damaged entries are parsed again
    # An edit is new content, so a new entry: the cache never answers for old code.
    (package_copy / "core.py").write_text("def f():\n    return 5\n")
    assert _hash() != first
    # Where nothing can be written, nothing is cached and the hash is the same.
    blocked = tmp_path / "blocked"
    blocked.write_text("a file, not a directory")
    monkeypatch.setenv("OMNILIDAR_CACHE_DIR", str(blocked))
    (package_copy / "core.py").write_text("def f():\n    return 1\n")
    assert _hash() == first


def test_a_results_envelope_leaves_torch_unimported_and_names_the_cpu():
    """A stage without torch (the data summary, the result tables) writes its envelope without
    importing torch for the device field: it ran on the CPU."""
    import subprocess

    code = ("import sys; from omnilidar.provenance import envelope; "
            "e = envelope('x', 'summarize-data', {}, {}, {}, 'synthetic'); "
            "print(e['device'].split(':')[0], 'torch' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["cpu", "False"]


def test_a_provenance_hash_follows_what_decides_a_job_and_not_the_versions(tmp_path):
    from omnilidar.checkpoints import job_provenance, provenance_differences, provenance_hash

    data = tmp_path / "in.txt"
    data.write_text("a")
    base = job_provenance("distill-generator", {"rounds": 3}, 0, {"teacher": data})
    other_versions = {**base, "versions": {"torch": "0.0"}}
    assert provenance_differences(base, other_versions) == []
    assert provenance_hash(other_versions) == provenance_hash(base)
    for changed in (job_provenance("distill-generator", {"rounds": 4}, 0, {"teacher": data}),
                    job_provenance("distill-generator", {"rounds": 3}, 1, {"teacher": data})):
        assert provenance_differences(base, changed) and provenance_hash(changed) != provenance_hash(base)
    data.write_text("b")  # the input's content, not its path, decides
    assert provenance_hash(job_provenance("distill-generator", {"rounds": 3}, 0, {"teacher": data})) != provenance_hash(base)
