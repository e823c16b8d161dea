"""worker.pipelines: a reconstruction's parameters resolve to the run configuration the worker
will run with (the same `core.config.load_config` the CLI uses)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

from core.config import CameraSplit, ResolvedRun, Views, load_config, validate
from worker.pipelines import PIPELINES, ReconstructParams, submitted_at


def test_top_level_parameters_and_config_agree():
    assert ReconstructParams(config={"gop": 5}).run_config().gop == 5  # not hidden by a default
    assert ReconstructParams(gop=3, config={"gop": 5}).run_config().gop == 3  # the explicit one
    assert ReconstructParams().run_config().gop == 20
    cfg = ReconstructParams(preset="test", checkpoint_every=7).run_config()
    assert cfg.checkpoint_every == 7 and cfg.train.schedule.iterations == 500


def test_a_bad_setting_is_named_under_config():
    with pytest.raises(ValueError) as err:
        ReconstructParams(config={"train": {"schedule": {"iterations": 0}}}).run_config()
    assert err.value.details[0]["path"] == "config.train.schedule.iterations"


def test_resolved_once_and_the_same_on_the_worker(tmp_path):
    params = ReconstructParams(preset="test", gop=2, checkpoint_every=9,
                               config={"train": {"seed": 3}})
    cfg = params.run_config()
    assert params.run_config() is cfg  # the API's checks and its resolution share it
    with pytest.raises(ValueError, match="frozen"):  # so it cannot go stale
        params.gop = 3
    assert (cfg.gop, cfg.checkpoint_every, cfg.train.seed) == (2, 9, 3)
    # The worker's params come back from the job's stored JSON and resolve to the same.
    stored = ReconstructParams.model_validate(params.model_dump(mode="json"))
    assert stored.run_config() == cfg
    from core.pipeline import reconstruct  # lazy: torch, which this module needs nowhere else

    resolved = ResolvedRun("test", "cap_x", ("000000",), cfg,
                           Views(CameraSplit("none", ("cam00",))))
    with pytest.raises(ValueError, match="not both"):
        reconstruct(tmp_path / "capture", tmp_path / "run", resolved=resolved, gop=3)
    assert not (tmp_path / "run").exists()


def test_the_bounds_are_the_configurations_own():
    """`gop`, `checkpoint_every` and `preset` are checked by the same types as RunConfig's."""
    for name, bad in (("gop", 10_001), ("checkpoint_every", 0), ("preset", "huge")):
        with pytest.raises(ValueError) as err:
            validate(ReconstructParams, {name: bad}, "params")
        assert err.value.details[0]["path"] == f"params.{name}"
        with pytest.raises(ValueError):
            load_config(**({"preset": bad} if name == "preset" else
                           {"overrides": {name: bad}}))


def test_each_pipeline_lists_the_kinds_of_what_it_writes():
    from core.rundir import classify

    written = {  # docs/design.md 3.3, docs/stream.md
        "reconstruct": ["frames/000000/gaussians.ply", "meshes/000000.ply", "meshes/000000.glb",
                        "renders/000000/cam00_rgb.png", "renders/000000/cam00_normal.png",
                        "renders/000000/cam00_ao.png", "renders/000000/cam00_depth.npy",
                        "renders/000000/cam00_relit.png", "plots/loss.png", "config.json",
                        "metrics.json", "sequence.json", "eval.json", "contact_sheet.png"],
        "relight": ["relit/000000/cam00.png", "relit/000000/cam00.exr", "relit/000000.mp4",
                    "relit/videos/cam00.mp4", "relit/relight.json"],
        "export": ["export/stream.dgss", "export/spz/000000.spz", "export/ply/000000.ply",
                   "export/export.json"],
    }
    for name, paths in written.items():
        assert {classify(p).kind for p in paths} == set(PIPELINES[name].artifacts), name
    assert {"mesh", "normal", "ao"} <= set(PIPELINES["reconstruct"].artifacts)


def _named(tree: ast.AST, names: set[str], anywhere: set[str]) -> list[int]:
    """Lines where code names one of `names` as a pipeline: compared with, passed as, assigned
    to or the default of something called *pipeline, or looked up in the registry; and any
    string constant of `anywhere` (docstrings aside)."""
    def const(node) -> bool:
        if isinstance(node, (ast.Tuple, ast.List, ast.Set)):
            return any(const(e) for e in node.elts)
        return isinstance(node, ast.Constant) and node.value in names

    def piped(node) -> bool:
        name = getattr(node, "attr", None) or getattr(node, "id", None) or ""
        return name.lower().endswith("pipeline")

    docs = {id(n.body[0].value) for n in ast.walk(tree)
            if isinstance(n, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef))
            and n.body and isinstance(n.body[0], ast.Expr)}
    hits = []
    for n in ast.walk(tree):
        sides = [n.left, *n.comparators] if isinstance(n, ast.Compare) else []
        args = n.args if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef)) else None
        defaults = list(zip((args.posonlyargs + args.args)[::-1], args.defaults[::-1])) + \
            list(zip(args.kwonlyargs, args.kw_defaults)) if args else []
        value = getattr(n, "value", None)
        first = value.args[0] if isinstance(value, ast.Call) and value.args else value
        if (any(map(const, sides)) and any(map(piped, sides))
                or isinstance(n, ast.keyword) and piped(ast.Name(n.arg or "")) and const(n.value)
                or any(piped(ast.Name(a.arg)) and d is not None and const(d) for a, d in defaults)
                or isinstance(n, (ast.Assign, ast.AnnAssign)) and const(first)
                and any(piped(x) for x in getattr(n, "targets", [getattr(n, "target", None)]))
                or isinstance(n, ast.Subscript) and getattr(n.value, "id", "") == "PIPELINES"
                and const(n.slice)
                or isinstance(n, ast.Call) and getattr(n.func, "id", "") == "get_pipeline"
                and any(map(const, n.args))
                or isinstance(n, ast.Constant) and n.value in anywhere and id(n) not in docs):
            hits.append(n.lineno)
    return hits


def test_a_pipeline_is_registered_in_one_place():
    """Only `worker/pipelines.py` names a pipeline (issue 40): what submits, runs and is run on
    is its `PIPELINES` entry's (routers find theirs by endpoint, a source is judged by
    `makes_results`); `core.rundir` says what kind a file is, the registry which pipeline
    writes each kind. A name that is no artifact kind ("reconstruct") appears nowhere else in
    the service, the worker or `core/rundir.py`."""
    import importlib

    from core.rundir import ARTIFACT_KINDS

    root = Path(__file__).resolve().parents[2]
    names = set(PIPELINES)
    bad = {}
    for path in sorted(p for d in ("service", "worker", "core") for p in (root / d).rglob("*.py")):
        rel = path.relative_to(root).as_posix()
        if rel == "worker/pipelines.py":
            continue
        strict = rel == "core/rundir.py" or not rel.startswith("core/")
        hits = _named(ast.parse(path.read_text()), names,
                      names - set(ARTIFACT_KINDS) if strict else set())
        if hits:
            bad[rel] = hits
    assert not bad, f"pipelines named outside worker/pipelines.py (file: lines): {bad}"
    for pipeline in PIPELINES.values():
        module, name = pipeline.execution.split(":")
        assert callable(getattr(importlib.import_module(module), name).run), pipeline.name
        assert submitted_at(pipeline.endpoint).endpoint == pipeline.endpoint, pipeline.name
    assert set(ARTIFACT_KINDS) == {k for p in PIPELINES.values() for k in p.artifacts}


@pytest.mark.parametrize("code", [
    'if job.pipeline == "relight": pass', 'ok = source.pipeline in ("export", "x")',
    'store.create_render(t, s, pipeline="relight")', 'def f(pipeline="export"): pass',
    'pipeline: str = Field("relight", max_length=32)', 'p = PIPELINES["export"]',
    'p = get_pipeline("relight")', 'RULES = (("frames/x", "ply", "reconstruct"),)'])
def test_the_naming_check_sees_each_way_of_naming(code):
    assert _named(ast.parse(code), set(PIPELINES), {"reconstruct"}) == [1]


def test_the_naming_check_passes_kinds_and_messages():
    code = 'kind = "relight"\nout = work / "export"\nmsg = f"a {x} reconstruct job"\n'
    assert _named(ast.parse(code), set(PIPELINES), {"reconstruct"}) == []
