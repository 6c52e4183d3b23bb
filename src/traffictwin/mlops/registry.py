"""MLflow Model Registry: challenger/champion quality gate, decision log, rollback.

Names (DESIGN.md "Tracking"): ``traffictwin-fusion-<cfg>`` and ``traffictwin-risk``; aliases
``champion`` and ``challenger`` (lowercase).

Promotion protocol (:func:`decide` then :func:`apply`):

1. The newly trained model (its MLflow run's logged model) is registered as a new version of
   its registered model (:func:`ensure_version`; a run that is already registered reuses its
   version, so re-running promotion after a no-op ``dvc repro`` registers nothing new).
2. Both the challenger and the version behind ``champion`` are **re-evaluated** on the same
   fixed held-out test set (the test split of the current data) by one ``evaluate`` callable
   that uses the evaluation stages' metric code. Stored figures are never compared across
   versions: a stored figure may come from a different test set (a retrain draws new data)
   or older metric code. The test-set fingerprint (dataset manifest hash + split) is recorded
   with every decision so that the figures can be traced to the data they were measured on.
   A champion that can no longer be evaluated on the current test set (e.g. trained for another
   grid) gets the figure NaN and is replaced by any challenger with a finite figure; the error
   is kept in the decision's reason.
3. ``champion`` moves to the challenger only if it is better by more than ``margin`` on the
   configured metric (:class:`Gate`); the first version of a model becomes champion.
   ``challenger`` always points to the newest candidate. Old versions stay registered.
4. Every decision is recorded on the challenger's model version as ``gate.*`` tags and as
   one JSON line in the promotion log, with both figures.

:func:`rollback` moves ``champion`` back to the previous champion (a stack kept in the
registered model's ``traffictwin.champion_history`` tag) or to an explicit version.

This module takes explicit arguments only (never params.yaml).
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from traffictwin.io.atomic import write_text_atomic

CHAMPION = "champion"
CHALLENGER = "challenger"
HISTORY_TAG = "traffictwin.champion_history"
HISTORY_MAX = 100
FUSION_PREFIX = "traffictwin-fusion"
RISK_NAME = "traffictwin-risk"

Action = Literal["first", "promoted", "rejected", "unchanged"]


class RegistryError(RuntimeError):
    """A registry operation cannot be done (missing model, alias, version or run)."""


def fusion_name(cfg: str, prefix: str = FUSION_PREFIX) -> str:
    """Registered-model name of fusion configuration ``cfg`` (e.g. ``traffictwin-fusion-D``)."""
    return f"{prefix}-{cfg}"


# --------------------------------------------------------------------------- gate (pure)


@dataclass(frozen=True)
class Gate:
    """Quality gate on one metric.

    ``metric``: key in the evaluation result (e.g. ``test/kld``); ``mode``: ``min`` (lower is
    better) or ``max``; ``margin``: absolute improvement (in the metric's units) the
    challenger must exceed to replace the champion (``>= 0``).
    """

    metric: str
    mode: Literal["min", "max"] = "min"
    margin: float = 0.0

    def __post_init__(self) -> None:
        if self.mode not in ("min", "max"):
            raise ValueError(f"gate mode must be 'min' or 'max', got {self.mode!r}")
        if not (
            isinstance(self.margin, (int, float))
            and math.isfinite(self.margin)
            and self.margin >= 0
        ):
            raise ValueError(f"gate margin must be a finite number >= 0, got {self.margin!r}")
        if not self.metric:
            raise ValueError("gate metric must be a non-empty metric name")

    def improvement(self, challenger: float, champion: float) -> float:
        """How much better the challenger is (positive = better), in metric units."""
        return (champion - challenger) if self.mode == "min" else (challenger - champion)

    def passes(self, challenger: float, champion: float | None) -> bool:
        """True if ``challenger`` should replace ``champion`` (``None``: no champion yet).

        A non-finite challenger figure never passes; a non-finite champion figure is beaten
        by any finite challenger.
        """
        if not math.isfinite(challenger):
            return False
        if champion is None or not math.isfinite(champion):
            return True
        return self.improvement(challenger, champion) > self.margin


# --------------------------------------------------------------------------- decisions


@dataclass
class Decision:
    """One gate decision (JSON-serialisable via :meth:`to_dict`)."""

    name: str
    challenger_version: str
    challenger_run_id: str
    champion_version: str | None
    metric: str
    mode: str
    margin: float
    challenger_value: float | None
    champion_value: float | None
    action: Action
    reason: str
    test_fingerprint: str = ""
    challenger_metrics: dict[str, float] = field(default_factory=dict)
    champion_metrics: dict[str, float] = field(default_factory=dict)
    timestamp: float = field(default_factory=time.time)

    @property
    def promotes(self) -> bool:
        return self.action in ("first", "promoted")

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["event"] = "promotion"
        d["time"] = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(self.timestamp))
        return d


def client(uri: str | None = None):
    """An ``MlflowClient`` on ``uri`` (default: :func:`traffictwin.mlops.tracking.tracking_uri`).

    Also points the fluent API (model loading, registration) at the same URI.
    """
    import mlflow
    from mlflow import MlflowClient

    from traffictwin.mlops.tracking import tracking_uri

    uri = uri or tracking_uri()
    mlflow.set_tracking_uri(uri)
    mlflow.set_registry_uri(uri)
    return MlflowClient(tracking_uri=uri, registry_uri=uri)


def version_uri(name: str, version: str | int) -> str:
    return f"models:/{name}/{version}"


def alias_uri(name: str, alias: str) -> str:
    return f"models:/{name}@{alias}"


def get_alias(cl, name: str, alias: str):
    """The model version behind ``name@alias``, or ``None`` if the model or alias does not exist."""
    from mlflow.exceptions import MlflowException

    try:
        return cl.get_model_version_by_alias(name, alias)
    except MlflowException:
        return None


def require_alias(cl, name: str, alias: str):
    """Like :func:`get_alias` but raises :class:`RegistryError` naming the model and alias."""
    mv = get_alias(cl, name, alias)
    if mv is None:
        known = _registered_names(cl)
        hint = (
            f"registered models: {', '.join(known)}"
            if known
            else "no models are registered yet (run `traffictwin promote`)"
        )
        raise RegistryError(f"model '{name}' has no version with alias '{alias}' ({hint})")
    return mv


def _registered_names(cl) -> list[str]:
    try:
        return sorted(m.name for m in cl.search_registered_models())
    except Exception:  # noqa: BLE001 - only for an error message
        return []


def ensure_version(
    cl, name: str, run_id: str, model_uri: str | None = None, tags: Mapping[str, Any] | None = None
):
    """The model version of ``name`` registered from ``run_id``; registers it if there is none.

    ``model_uri``: the logged model to register (default ``runs:/<run_id>/model``).
    Raises :class:`RegistryError` if the run does not exist.
    """
    import mlflow
    from mlflow.exceptions import MlflowException

    try:
        cl.get_run(run_id)
    except MlflowException:
        raise RegistryError(
            f"MLflow run '{run_id}' (for model '{name}') not found at {mlflow.get_tracking_uri()}"
        ) from None
    try:
        existing = cl.search_model_versions(f"name='{name}' and run_id='{run_id}'")
    except MlflowException:
        existing = []
    if existing:
        return max(existing, key=lambda v: int(v.version))
    try:
        cl.get_registered_model(name)
    except MlflowException:
        cl.create_registered_model(
            name,
            description=f"traffictwin model '{name}' (promotion gate: traffictwin.mlops.registry)",
        )
    try:
        mv = mlflow.register_model(
            model_uri or f"runs:/{run_id}/model",
            name,
            tags={k: str(v) for k, v in (tags or {}).items()},
        )
    except MlflowException as exc:
        raise RegistryError(
            f"cannot register run '{run_id}' as '{name}' from {model_uri or f'runs:/{run_id}/model'}: {exc}"
        ) from None
    return cl.get_model_version(name, mv.version)


def _metric(result: Mapping[str, float], metric: str, who: str) -> float:
    if metric not in result:
        raise RegistryError(
            f"evaluation of {who} returned no metric '{metric}' (got {sorted(result)})"
        )
    return float(result[metric])


def decide(
    cl,
    name: str,
    challenger,
    evaluate: Callable[[str], Mapping[str, float]],
    gate: Gate,
    *,
    test_fingerprint: str = "",
    champion_alias: str = CHAMPION,
    force: bool = False,
) -> Decision:
    """Evaluate ``challenger`` (a ModelVersion) and the current champion with ``evaluate``; decide.

    ``evaluate(model_uri) -> {metric: value}`` must load the model and score it on the fixed
    held-out test set; it is called for both versions so their figures are comparable.
    Nothing in the registry changes here (see :func:`apply`). A challenger already decided
    against the same champion on the same test set is not re-evaluated (``unchanged``) unless
    ``force``.
    """
    champ = get_alias(cl, name, champion_alias)
    common = dict(
        name=name,
        challenger_version=str(challenger.version),
        challenger_run_id=challenger.run_id or "",
        metric=gate.metric,
        mode=gate.mode,
        margin=float(gate.margin),
        test_fingerprint=test_fingerprint,
    )
    if champ is not None and str(champ.version) == str(challenger.version):
        return Decision(
            **common,
            champion_version=str(champ.version),
            challenger_value=None,
            champion_value=None,
            action="unchanged",
            reason="challenger is already the champion",
        )
    tags = challenger.tags or {}
    if (
        not force
        and "gate.decision" in tags
        and champ is not None
        and tags.get("gate.champion_version") == str(champ.version)
        and tags.get("gate.test_fingerprint", "") == test_fingerprint
    ):
        return Decision(
            **common,
            champion_version=str(champ.version),
            challenger_value=None,
            champion_value=None,
            action="unchanged",
            reason=f"already decided against champion v{champ.version} on this test set "
            f"({tags['gate.decision']})",
        )
    ch_metrics = {k: float(v) for k, v in evaluate(version_uri(name, challenger.version)).items()}
    ch_val = _metric(ch_metrics, gate.metric, f"{name} v{challenger.version}")
    if champ is None:
        ok = math.isfinite(ch_val)
        return Decision(
            **common,
            champion_version=None,
            challenger_value=ch_val,
            champion_value=None,
            action="first" if ok else "rejected",
            reason="no champion yet: first model becomes champion"
            if ok
            else f"{gate.metric} is not finite",
            challenger_metrics=ch_metrics,
        )
    cp_error = ""
    try:
        cp_metrics = {k: float(v) for k, v in evaluate(version_uri(name, champ.version)).items()}
        cp_val = _metric(cp_metrics, gate.metric, f"{name} v{champ.version} (champion)")
    except Exception as exc:  # noqa: BLE001 - a champion that no longer runs on the current test set
        cp_metrics, cp_val = {}, float("nan")
        cp_error = f"champion v{champ.version} could not be evaluated on this test set ({type(exc).__name__}: {exc}); "
    better = gate.passes(ch_val, cp_val)
    word = "lower" if gate.mode == "min" else "higher"
    imp = (
        gate.improvement(ch_val, cp_val)
        if math.isfinite(ch_val) and math.isfinite(cp_val)
        else float("nan")
    )
    reason = (
        f"{cp_error}{gate.metric}: challenger {ch_val:.6g} vs champion {cp_val:.6g} ({word} is better; "
        f"improvement {imp:.3g} {'>' if better else '<='} margin {gate.margin:g})"
    )
    return Decision(
        **common,
        champion_version=str(champ.version),
        challenger_value=ch_val,
        champion_value=cp_val,
        action="promoted" if better else "rejected",
        reason=reason,
        challenger_metrics=ch_metrics,
        champion_metrics=cp_metrics,
    )


def champion_history(cl, name: str) -> list[str]:
    """Versions that became champion, oldest first (the rollback stack)."""
    try:
        tags = cl.get_registered_model(name).tags or {}
    except Exception:  # noqa: BLE001
        return []
    try:
        hist = json.loads(tags.get(HISTORY_TAG, "[]"))
    except json.JSONDecodeError:
        return []
    return [str(v) for v in hist]


def _set_history(cl, name: str, hist: Sequence[str]) -> None:
    cl.set_registered_model_tag(name, HISTORY_TAG, json.dumps(list(hist)[-HISTORY_MAX:]))


def apply(
    cl,
    decision: Decision,
    *,
    log_path: str | Path | None = None,
    champion_alias: str = CHAMPION,
    challenger_alias: str = CHALLENGER,
) -> None:
    """Record ``decision`` (tags + log line), set ``challenger``, and move ``champion`` if it promotes.

    An ``unchanged`` decision changes nothing and is not logged.
    """
    if decision.action == "unchanged":
        return
    name, ver = decision.name, decision.challenger_version
    tags = {
        "gate.decision": decision.action,
        "gate.metric": decision.metric,
        "gate.mode": decision.mode,
        "gate.margin": repr(decision.margin),
        "gate.challenger_value": repr(decision.challenger_value),
        "gate.champion_value": repr(decision.champion_value),
        "gate.champion_version": str(decision.champion_version or ""),
        "gate.test_fingerprint": decision.test_fingerprint,
        "gate.reason": decision.reason[:4000],
        "gate.time": decision.to_dict()["time"],
    }
    for k, v in tags.items():
        cl.set_model_version_tag(name, ver, k, v)
    cl.set_registered_model_alias(name, challenger_alias, ver)
    if decision.promotes:
        cl.set_registered_model_alias(name, champion_alias, ver)
        _set_history(cl, name, [*champion_history(cl, name), ver])
    if log_path is not None:
        append_log(log_path, decision.to_dict())


def rollback(
    cl,
    name: str,
    version: str | int | None = None,
    *,
    log_path: str | Path | None = None,
    champion_alias: str = CHAMPION,
) -> dict[str, Any]:
    """Move ``champion`` of ``name`` back: to ``version`` if given, else to the previous champion.

    Without ``version`` the current champion is popped off the history stack, so repeated
    rollbacks walk further back. Returns the logged record. Raises :class:`RegistryError` if the
    model, version or a previous champion does not exist.
    """
    from mlflow.exceptions import MlflowException

    try:
        cl.get_registered_model(name)
    except MlflowException:
        known = _registered_names(cl)
        raise RegistryError(
            f"no registered model '{name}'"
            + (f" (registered: {', '.join(known)})" if known else "")
        ) from None
    current = get_alias(cl, name, champion_alias)
    cur = str(current.version) if current is not None else None
    hist = champion_history(cl, name)
    if version is None:
        while hist and hist[-1] == cur:
            hist.pop()
        if not hist:
            raise RegistryError(
                f"model '{name}': no previous champion to roll back to (current champion: v{cur}); "
                f"pass --version"
            )
        target = hist[-1]
    else:
        target = str(version)
        try:
            cl.get_model_version(name, target)
        except MlflowException:
            raise RegistryError(f"model '{name}' has no version {target}") from None
        hist.append(target)
    cl.set_registered_model_alias(name, champion_alias, target)
    _set_history(cl, name, hist)
    now = time.time()
    cl.set_model_version_tag(name, target, "gate.rollback_from", str(cur or ""))
    record = {
        "event": "rollback",
        "name": name,
        "from_version": cur,
        "to_version": target,
        "timestamp": now,
        "time": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(now)),
    }
    if log_path is not None:
        append_log(log_path, record)
    return record


def append_log(path: str | Path, record: Mapping[str, Any]) -> None:
    """Append one JSON line to ``path`` (the whole file is rewritten atomically)."""
    path = Path(path)
    old = path.read_text() if path.exists() else ""
    if old and not old.endswith("\n"):
        old += "\n"
    line = json.dumps(_finite(dict(record)), sort_keys=True, default=_json_default, allow_nan=False)
    write_text_atomic(path, old + line + "\n")


def _finite(obj: Any) -> Any:
    """Non-finite floats -> None, recursively (strict JSON lines)."""
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite(v) for v in obj]
    if isinstance(obj, (float, np.floating)):
        return float(obj) if math.isfinite(float(obj)) else None
    return obj


def read_log(path: str | Path) -> list[dict[str, Any]]:
    """All records of a promotion log (empty if it does not exist)."""
    path = Path(path)
    if not path.exists():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def _json_default(o: Any) -> Any:
    try:
        import numpy as np

        if isinstance(o, np.generic):
            return o.item()
    except ImportError:  # pragma: no cover
        pass
    return str(o)


def status(
    cl, names: Sequence[str], champion_alias: str = CHAMPION, challenger_alias: str = CHALLENGER
) -> list[dict[str, Any]]:
    """Champion/challenger version and their last recorded figures for each registered model."""
    rows = []
    for n in names:
        row: dict[str, Any] = {"name": n}
        for alias in (champion_alias, challenger_alias):
            mv = get_alias(cl, n, alias)
            row[alias] = (
                None
                if mv is None
                else {
                    "version": str(mv.version),
                    "run_id": mv.run_id,
                    "value": (mv.tags or {}).get("gate.challenger_value"),
                    "decision": (mv.tags or {}).get("gate.decision"),
                }
            )
        row["history"] = champion_history(cl, n)
        rows.append(row)
    return rows


# --------------------------------------------------------------------------- candidates + evaluators


@dataclass
class Candidate:
    """A newly trained model to put through the gate: its registered name and MLflow run."""

    name: str
    run_id: str
    model_uri: str | None
    meta_path: Path
    meta: dict[str, Any] = field(default_factory=dict)


def read_candidate(name: str, model_dir: str | Path) -> Candidate:
    """The candidate behind ``<model_dir>/model_meta.json`` (keys ``mlflow_run_id``/``run_id``,
    optional ``mlflow_model_uri``/``model_uri``). Errors name the file and the missing key."""
    meta_path = Path(model_dir) / "model_meta.json"
    if not meta_path.exists():
        raise RegistryError(f"{meta_path}: not found (train the model first: `dvc repro`)")
    try:
        meta = json.loads(meta_path.read_text())
    except json.JSONDecodeError as exc:
        raise RegistryError(f"{meta_path}: not valid JSON ({exc})") from None
    run_id = meta.get("mlflow_run_id") or meta.get("run_id")
    if not run_id:
        raise RegistryError(
            f"{meta_path}: no MLflow run id (key 'mlflow_run_id'); was the model trained with tracking enabled?"
        )
    uri = meta.get("mlflow_model_uri") or meta.get("model_uri")
    return Candidate(
        name=name,
        run_id=str(run_id),
        model_uri=str(uri) if uri else None,
        meta_path=meta_path,
        meta=meta,
    )


def load_registered(uri: str):
    """Load an MLflow PyTorch model (``models:/name/version`` or ``models:/name@alias``) on CPU, eval mode."""
    import mlflow.pytorch

    model = mlflow.pytorch.load_model(uri, map_location="cpu")
    return model.eval()


def _take_first(order_key: np.ndarray, k: int | None) -> np.ndarray:
    idx = np.argsort(order_key, kind="stable")
    return idx if k is None or k <= 0 else idx[:k]


def fusion_test_set(
    data_root: str | Path, split: str = "test", max_pairs: int | None = None
) -> tuple[np.ndarray, np.ndarray, str]:
    """Gate test set of a prealigned dataset: ``inputs (N,4,H,W)``, ``label (N,2,H,W)`` of the first
    ``max_pairs`` pairs by ``pair_id`` (a fixed selection), and its fingerprint."""
    from traffictwin.io.shards import Dataset

    ds = Dataset(data_root, kind="prealigned")
    a = ds.load_all(split, keys=["inputs", "label", "pair_id"])
    sel = _take_first(np.asarray(a["pair_id"]), max_pairs)
    fp = f"prealigned:{ds.manifest_hash()[:16]}:{split}:{len(sel)}"
    return (
        np.ascontiguousarray(a["inputs"][sel], np.float32),
        np.ascontiguousarray(a["label"][sel], np.float32),
        fp,
    )


def fusion_evaluator(
    inputs: np.ndarray, label: np.ndarray, batch_size: int = 8
) -> Callable[[str], dict[str, float]]:
    """``evaluate(model_uri)``: fused masses of the model on ``inputs``, scored with
    :mod:`traffictwin.fusion.metrics` (the evaluate_fusion stage's code) as ``test/<name>``."""
    from traffictwin.fusion import metrics as fm
    from traffictwin.fusion.model_io import predict_masses

    def evaluate(uri: str) -> dict[str, float]:
        model = load_registered(uri)
        m, _ = predict_masses(model, inputs, batch_size=batch_size)
        agg = fm.aggregate(fm.per_sample_metrics(label, m))
        return {f"test/{k}": float(v) for k, v in agg.items()}

    return evaluate


def unwrap_risk_net(model):
    """The :class:`~traffictwin.risk.dave2.Dave2` inside an MLflow-loaded risk model."""
    from traffictwin.risk.dave2 import Dave2

    for cand in (model, getattr(model, "net", None)):
        if isinstance(cand, Dave2):
            return cand
    raise RegistryError(
        f"registered risk model is a {type(model).__name__}, expected a Dave2 (or a wrapper with .net)"
    )


def risk_test_set(
    risk_root: str | Path,
    disparity_root: str | Path,
    orb_csv: str | Path | None,
    split: str = "test",
    max_frames: int | None = None,
) -> tuple[dict[str, np.ndarray], str]:
    """Raw test frames of the ORB-passed split (``left``, ``disp_sgm``, ``disp_gt``, ``speed`` and every
    ``risk*`` label column), the first ``max_frames`` by frame id, and the fingerprint."""
    from traffictwin.io.shards import sha256_file
    from traffictwin.risk.training import RiskSource

    src = RiskSource(risk_root, disparity_root, orb_csv)
    frames = src.split_frames(split).sort_values("frame_id", kind="stable")
    if max_frames:
        frames = frames.iloc[:max_frames]
    parts: dict[str, list[np.ndarray]] = {"left": [], "disp_sgm": [], "disp_gt": []}
    rows_all = []
    for rows, arrays in src.iter_arrays(frames, ["left", "disp_sgm", "disp_gt"]):
        for k in parts:
            parts[k].append(arrays[k])
        rows_all.append(rows)
    if not rows_all:
        raise RegistryError(f"{risk_root}: no ORB-passed frames in split '{split}' to evaluate on")
    import pandas as pd

    rows = pd.concat(rows_all)
    data = {k: np.concatenate(v) for k, v in parts.items()}
    data["speed"] = rows["speed"].to_numpy(np.float32)
    for c in rows.columns:
        if c.startswith("risk"):
            data[f"label:{c}"] = rows[c].to_numpy(np.float32)
    orb_fp = sha256_file(orb_csv)[:8] if orb_csv else "none"
    fp = (
        f"risk:{src.risk.manifest_hash()[:16]}:disp:{src.disparity.manifest_hash()[:8] if src.disparity else 'none'}"
        f":orb:{orb_fp}:{split}:{len(rows)}"
    )
    return data, fp


def risk_evaluator(
    data: Mapping[str, np.ndarray],
    label: str,
    thresholds_s: Sequence[float] = (1.5, 1.0),
    thw_cap: float = 10.0,
    batch_size: int = 256,
) -> Callable[[str], dict[str, float]]:
    """``evaluate(model_uri)``: predicted risk of the model (its own preprocessing) on the raw test
    frames, scored with :func:`traffictwin.risk.evaluation.evaluate` against ``label``.

    Returns ``test/mse``, ``test/mae``, … and ``test/accuracy`` (+ ``test/balanced_accuracy``) at the
    first threshold."""
    from traffictwin.risk import evaluation as rm
    from traffictwin.risk.model_io import RiskModel

    key = f"label:{label}"
    if key not in data:
        have = sorted(k[6:] for k in data if k.startswith("label:"))
        raise RegistryError(f"risk label column '{label}' not in frames.csv (has {have})")
    y = np.asarray(data[key], np.float32)

    def evaluate(uri: str) -> dict[str, float]:
        rmodel = RiskModel(net=unwrap_risk_net(load_registered(uri)))
        p = rmodel.predict(
            left_bgr=data["left"],
            disp_sgm=data["disp_sgm"],
            disp_gt=data["disp_gt"],
            speed=data["speed"],
            batch_size=batch_size,
        )
        res = rm.evaluate(y, p, thresholds_s=tuple(thresholds_s), thw_cap=thw_cap)
        out = {k: float(v) for k, v in res.items() if isinstance(v, (int, float))}
        first = res[f"at_{float(thresholds_s[0]):g}s"]
        out["test/accuracy"] = float(first["accuracy"])
        out["test/balanced_accuracy"] = float(first["balanced_accuracy"])
        return out

    return evaluate
