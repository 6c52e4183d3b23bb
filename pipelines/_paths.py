"""Every path a stage reads or writes, derived in one place (dvc.yaml spells the same layout).

Configurations (``configurations.<cfg>``) and risk variants (``risk_model.run_variants``) come
from params.yaml; the folders below are the repository layout, which only the workflow layer
(``pipelines/``) knows. The library receives these paths as explicit arguments.
"""

from __future__ import annotations

from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

PARAMS = ROOT / "params.yaml"
CONF = ROOT / "conf"
DVC_YAML = ROOT / "dvc.yaml"

DATA = ROOT / "data"
MODELS = ROOT / "models"
REPORTS = ROOT / "reports"
METRICS = REPORTS / "metrics"
PLOTS = REPORTS / "plots"
FIGURES = REPORTS / "figures"
TIMINGS = REPORTS / "timings"
# training state of a killed training stage (traffictwin.resume); no DVC output, git-ignored
RESUME = ROOT / ".cache" / "traffictwin" / "resume"

# fusion
FUSION_DATA = DATA / "fusion"
PREALIGNED = DATA / "prealigned"
REGISTERED = DATA / "registered"
FUSION_MODELS = MODELS / "fusion"
REGISTRATION_MODELS = MODELS / "registration"

# twin
TWIN_DATA = DATA / "twin"

# risk
RISK_DATA = DATA / "risk"
DISPARITY = DATA / "disparity"
ORB_CSV = DATA / "orb" / "orb.csv"
STEREO_LEARNED = DATA / "stereo_learned"
STEREO_MODEL = MODELS / "stereo" / "learned"
#: the same network trained without the held-out road templates (generalisation)
STEREO_HOLDOUT_MODEL = MODELS / "stereo" / "holdout"
RISK_MODELS = MODELS / "risk"


def prealigned(cfg: str) -> Path:
    """``data/prealigned/<cfg>``: map 2 warped by the noisy pose of configuration ``cfg`` (or of
    the training-noise mixture, ``mixed``)."""
    return PREALIGNED / cfg


def registered(cfg: str) -> Path:
    """``data/registered/<cfg>``: map 2 warped by the classical registration estimate (register@<cfg>)."""
    return REGISTERED / cfg


def fusion_data_dir(inputs: str, cfg: str) -> Path:
    """``data/<inputs>/<cfg>``: the training pairs of a network (``inputs``: prealigned | registered)."""
    return {"prealigned": prealigned, "registered": registered}[inputs](cfg)


def fusion_model_dir(name: str = "network") -> Path:
    """``models/fusion/<name>``: the one fusion network (``network``) or fusion variant ``name``
    (model.ckpt, model_meta.json)."""
    return FUSION_MODELS / name


def registration_model_dir() -> Path:
    """``models/registration/learned``: the one learned registration (every noise level)."""
    return REGISTRATION_MODELS / "learned"


def risk_model_dir(variant: str) -> Path:
    """``models/risk/<variant>``: one trained risk-network variant."""
    return RISK_MODELS / variant


#: ``models/risk_shipped``: the risk predictor chosen on validation (select_risk); what users get
SHIPPED_RISK_MODEL = MODELS / "risk_shipped"


HYBRID_MODELS = MODELS / "risk_hybrid"


def hybrid_model_dir(run: str) -> Path:
    """``models/risk_hybrid/<run>``: one seed of the corridor hybrid (train_risk_hybrid)."""
    return HYBRID_MODELS / run


def metrics_file(name: str) -> Path:
    """``reports/metrics/<name>.json``."""
    return METRICS / f"{name}.json"


def plot_file(name: str) -> Path:
    """``reports/plots/<name>.csv``."""
    return PLOTS / f"{name}.csv"


def figure_file(name: str) -> Path:
    """``reports/figures/<name>.png``."""
    return FIGURES / f"{name}.png"


def resume_dir(stage: str) -> Path:
    """``.cache/traffictwin/resume/<stage>`` (``@`` as ``-``): where a training stage keeps its
    ``last.ckpt`` until it finishes, so a re-run after a kill resumes (outside the DVC outputs)."""
    return RESUME / stage.replace("@", "-")


def run_record_file(stage: str) -> Path:
    """``reports/timings/<stage>.json`` (``@`` written as ``-``): the run record of DVC stage ``stage``
    (wall time, MLflow run id, throughput), committed to git but never a DVC output or dependency."""
    return TIMINGS / f"{stage.replace('@', '-')}.json"
