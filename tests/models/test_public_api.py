"""models/ and the README's examples use only the public API: the names in ``bayespd.__all__``
and ``bayespd.infer.__all__`` (and other models)."""
import ast
import re
from pathlib import Path

import pytest

import bayespd
import bayespd.infer

ROOT = Path(__file__).resolve().parents[2]
PUBLIC = {"bayespd": set(bayespd.__all__), "bayespd.infer": set(bayespd.infer.__all__)}


def _uses(tree: ast.AST):
    """(module, name) for each name imported from a bayespd module, and ("bayespd", name)
    for each attribute read from the ``bp`` alias."""
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("bayespd"):
            yield from ((node.module, alias.name) for alias in node.names)
        elif isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id == "bp":
            yield "bayespd", node.attr


def _private(uses) -> list:
    return [(module, name) for module, name in uses
            if not module.startswith("bayespd.models") and name not in PUBLIC.get(module, ())]


@pytest.mark.parametrize("path", sorted((ROOT / "models").glob("*.py")), ids=lambda p: p.name)
def test_models_import_only_the_public_api(path):
    assert _private(_uses(ast.parse(path.read_text()))) == []


def test_the_readme_examples_use_only_the_public_api():
    blocks = re.findall(r"```python\n(.*?)```", (ROOT / "README.md").read_text(), flags=re.S)
    assert blocks
    uses = [use for block in blocks for use in _uses(ast.parse(block))]
    assert ("bayespd", "Scene") in uses
    assert _private(uses) == []


def test_a_private_import_is_caught():
    assert _private(_uses(ast.parse("from bayespd.gmrf import GMRF\nbp.sparse"))) == [
        ("bayespd.gmrf", "GMRF"), ("bayespd", "sparse")]
