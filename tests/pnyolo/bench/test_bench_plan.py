"""One prediction plan and one runner (issue 86, item 2): a plan made from the kinds' decodings says which rows a
comparison scores, the (model, condition) pairs those rows read follow from it, and ``predict_plan`` predicts each
pair once; the bench's test stage and the commands (``pnyolo-eval``, ``pnyolo-track``) predict through it."""
from __future__ import annotations

import ast

import pytest
import torch
from test_pnyolo_common import TINY, for_kind, make_dataset

from pnyolo.bench.plan import COVERAGE, PredictionPlan, predict_plan
from pnyolo.config import load_config
from pnyolo.cooperation.pose_noise import PoseNoise
from pnyolo.data.dataset import MultiViewDataset
from pnyolo.engine.predict import Condition, Trained
from pnyolo.evaluation.evaluate import LATE_FUSION, OWN_VIEW, Entry, LateInto, evaluate_models
from pnyolo.models import build_model
from repo_paths import REPO

PNY, BEV, SV = "pixelnerf-yolo", "bev", "single-view"


@pytest.fixture(scope="module")
def three(tmp_path_factory):
    """The three kinds, untrained, on one grid, and a two-scenario test split."""
    root = make_dataset(tmp_path_factory.mktemp("plan") / "ds", n_scenarios=2)
    trained = {}
    for kind in (PNY, BEV, SV):
        cfg = load_config(None, for_kind(TINY, [f"model.kind={kind}", "eval.conf_threshold=0.02"]))
        torch.manual_seed(0)
        trained[kind] = Trained(None, build_model(cfg, 2).eval(), cfg)
    ds = MultiViewDataset(root, "test", trained[BEV].config, training=False, every_camera=True)
    return trained, ds


def test_a_plan_gives_each_kind_the_rows_its_decoding_allows(three):
    """Own view for the kinds that read other views, late fusion for those with 3D detections, coverage for the
    multi-view kinds that say where they query; a model's conditions are what its rows read, each once."""
    trained, _ = three
    decodings = {k: t.decoding for k, t in trained.items()}
    plan = PredictionPlan.of(decodings, fuse=(PNY, SV), late_into=LateInto(BEV, SV, 0.1, 0.1))
    assert plan.models == (PNY, BEV, SV)
    assert plan.own_view == (PNY, BEV) and plan.late == (PNY, BEV) and plan.coverage == (PNY, BEV)
    assert plan.conditions(PNY) == plan.conditions(BEV) == (Condition(samples=True), Condition(own_view=True))
    assert plan.conditions(SV) == (Condition(),)  # the ego of late fusion into it reads its own clean items
    only = PredictionPlan.of(decodings, rows=(), late=(BEV,), pose_noise=PoseNoise(0.2, 0.2, 0))
    assert (only.own_view, only.late, only.coverage) == ((), (BEV,), ())
    assert only.conditions(SV) == (Condition(pose_noise=PoseNoise(0.2, 0.2, 0)),)
    assert PredictionPlan((BEV,), late=(BEV,), clean=False).conditions(BEV) == (Condition(own_view=True),)
    assert PredictionPlan.of(decodings, rows=(COVERAGE,)).coverage == (PNY, BEV)
    with pytest.raises(ValueError, match="unknown row"):
        PredictionPlan.of(decodings, rows=("fusion of everything",))
    with pytest.raises(ValueError, match=r"\['ego'\], not among"):
        PredictionPlan((BEV,), late_into=LateInto(BEV, "ego", 0.1, 0.1)).check()


def test_the_runner_predicts_each_pair_once_and_scoring_makes_no_forward(three, monkeypatch):
    """``predict_plan`` makes one forward per item and (model, condition); the comparison it returns holds every
    row the plan names and is scored without another forward."""
    import pnyolo.engine.predict as engine

    trained, ds = three
    plan = PredictionPlan.of({k: t.decoding for k, t in trained.items()}, fuse=(PNY, SV),
                             late_into=LateInto(BEV, SV, 0.05, 0.05))
    calls = []
    real = engine.predict_item
    monkeypatch.setattr(engine, "predict_item", lambda m, item, *a, **k: calls.append(
        (m.kind, bool(k.get("own_view_only")), bool(k.get("return_samples")))) or real(m, item, *a, **k))
    comparison = predict_plan(plan, trained, ds)
    expected = {(k, c.own_view, c.samples) for k in plan.models for c in plan.conditions(k)}
    assert sorted(calls) == sorted(e for e in expected for _ in range(len(ds)))
    assert comparison.models[SV].own is None and comparison.models[SV].cars is None  # nothing asked of it alone
    assert comparison.models[BEV].cars is not None and comparison.models[PNY].own is not None
    assert set(comparison.coverage) == {PNY, BEV}
    monkeypatch.setattr(engine, "predict_item", lambda *a, **k: pytest.fail("a forward pass while scoring"))
    rows = set(evaluate_models(comparison, ds))
    assert rows == {Entry(PNY), Entry(BEV), Entry(SV), Entry(PNY, "fusion", SV), Entry(PNY, OWN_VIEW),
                    Entry(BEV, OWN_VIEW), Entry(PNY, LATE_FUSION), Entry(BEV, LATE_FUSION),
                    Entry(BEV, LATE_FUSION, SV)}


def test_the_cars_messages_may_come_from_another_dataset_but_an_ablation_may_not(three):
    """Under a delay pnyolo-eval's late fusion takes the cars' messages from the whole sequences (``senders``); an
    own-view ablation is of the scored items themselves, so a plan asking for one with other senders is refused."""
    trained, ds = three
    late = PredictionPlan((BEV,), late=(BEV,))
    comparison = predict_plan(late, trained, ds, senders=ds)
    assert comparison.models[BEV].own is None and comparison.models[BEV].cars is not None
    with pytest.raises(ValueError, match="own-view ablation"):
        predict_plan(PredictionPlan((BEV,), own_view=(BEV,)), trained, ds, senders=ds)


def _calls_of_predict(path) -> list[int]:
    """Lines of ``path`` that call the engine's ``predict`` (by that name)."""
    tree = ast.parse(path.read_text())
    return [n.lineno for n in ast.walk(tree) if isinstance(n, ast.Call) and isinstance(n.func, ast.Name)
            and n.func.id == "predict"]


def test_outside_the_plan_only_training_and_the_api_call_predict():
    """The bench (validation sweeps, the test stage, pose noise, delays, tracks) and the commands (pnyolo-eval,
    pnyolo-track, pnyolo-predict, by torch or ONNX Runtime) predict through the plan; the engine's ``predict`` is
    called directly only by training's validation and the inference API (one item at a time)."""
    callers = {str(p.relative_to(REPO)) for p in (REPO / "pnyolo").rglob("*.py")
               if p.name != "predict.py" or p.parent.name != "engine" if _calls_of_predict(p)}
    assert callers == {"pnyolo/bench/plan.py", "pnyolo/training/train.py", "pnyolo/inference.py"}, callers
