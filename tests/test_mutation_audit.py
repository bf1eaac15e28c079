"""The mutation audit (`scripts/mutation_audit.py`, listed in docs/testing.md) still applies to the
tree: a mutation whose line was rewritten would stop the audit, and docs/testing.md would go on
claiming a catch that nobody can rerun."""

import importlib.util
import sys

from conftest import ROOT


def _mutations() -> list:
    spec = importlib.util.spec_from_file_location("mutation_audit", ROOT / "scripts" / "mutation_audit.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclasses look their module up there
    spec.loader.exec_module(module)
    return module.MUTATIONS


def test_every_mutation_applies_once_names_real_tests_and_is_listed():
    mutations = _mutations()
    # the audit's own rule (`apply`): the text to replace occurs exactly once
    stale = [f"{k}. {m.name} ({m.file})" for k, m in enumerate(mutations, 1)
             if m.file and (ROOT / m.file).read_text().count(m.old) != 1]
    assert not stale, f"the text to replace is not found exactly once: {stale}"
    for k, m in enumerate(mutations, 1):
        assert m.file or m.script, m.name
        for test in m.tests:  # its files and test functions (a parametrized id's function)
            path, _, name = test.partition("::")
            assert (ROOT / path).is_file(), (k, test)
            if name:
                assert f"def {name.split('[')[0]}(" in (ROOT / path).read_text(), (k, test)
    listed = (ROOT / "docs" / "testing.md").read_text()
    unlisted = [k for k, m in enumerate(mutations, 1) if f"\n{k}. {m.name}: " not in listed]
    assert not unlisted, f"mutations without their audit output in docs/testing.md: {unlisted}"
    missed = [k for k, m in enumerate(mutations, 1) if f"\n{k}. {m.name}: CAUGHT by " not in listed]
    assert not missed, f"mutations docs/testing.md lists as not caught: {missed}"
