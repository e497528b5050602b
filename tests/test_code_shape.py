"""The shape of the code, read with `ast`: one back-projection in the package, a localizer
step that is a fixed chain of stages behind the keyframe rule, and at most 150 config keys."""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE_DIR = Path(__file__).resolve().parents[1] / "bimfactor"


def _trees() -> list[tuple[Path, ast.Module]]:
    return [(path, ast.parse(path.read_text(), str(path))) for path in sorted(PACKAGE_DIR.rglob("*.py"))]


def _is_backprojection(node: ast.AST) -> bool:
    """`(u - K.cx) / K.fx` or `(v - K.cy) / K.fy`: a pixel offset from the principal point over the focal length."""
    if not (isinstance(node, ast.BinOp) and isinstance(node.op, ast.Div)):
        return False
    left, right = node.left, node.right
    return (
        isinstance(left, ast.BinOp)
        and isinstance(left.op, ast.Sub)
        and isinstance(left.right, ast.Attribute)
        and left.right.attr in ("cx", "cy")
        and isinstance(right, ast.Attribute)
        and right.attr in ("fx", "fy")
    )


def test_one_back_projection_function_in_the_package() -> None:
    # every pixel-to-ray division in bimfactor/, by the function that holds it
    places = sorted(
        f"{path.relative_to(PACKAGE_DIR.parent)}:{function.name}"
        for path, tree in _trees()
        for function in ast.walk(tree)
        if isinstance(function, ast.FunctionDef)
        for node in ast.walk(function)
        if _is_backprojection(node)
    )
    assert places == ["bimfactor/types.py:backproject"] * 2, places


def _method(path: Path, cls: str, name: str) -> ast.FunctionDef:
    tree = ast.parse(path.read_text())
    owner = next(n for n in tree.body if isinstance(n, ast.ClassDef) and n.name == cls)
    return next(n for n in owner.body if isinstance(n, ast.FunctionDef) and n.name == name)


def test_the_localizer_step_is_a_fixed_chain_of_stages() -> None:
    step = _method(PACKAGE_DIR / "pipeline.py", "Localizer", "step")
    assert step.end_lineno is not None and step.end_lineno - step.lineno + 1 <= 25
    # no branch on the variant or anything else (a variant is its chain of stages, chosen when the localizer is
    # built), but the keyframe rule's: a frame that is not a keyframe goes no further
    branches = [node for node in ast.walk(step) if isinstance(node, ast.If | ast.IfExp | ast.Match)]
    assert len(branches) == 1 and "self.due(frame)" in ast.unparse(branches[0].test), [b.lineno for b in branches]
    names = {node.attr for node in ast.walk(step) if isinstance(node, ast.Attribute)}
    assert {"keyframe", "filter", "_stages"} <= names and "variant" not in names


def test_the_configuration_has_at_most_150_keys() -> None:
    """Counted as a user sees them: the leaves of `bimfactor config --all`."""
    import yaml
    from typer.testing import CliRunner

    from bimfactor.cli import app

    result = CliRunner().invoke(app, ["config", "--all"])
    assert result.exit_code == 0, result.output

    def leaves(node: object) -> int:
        return sum(leaves(v) for v in node.values()) if isinstance(node, dict) else 1

    assert 100 < leaves(yaml.safe_load(result.stdout)) <= 150
