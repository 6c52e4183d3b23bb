"""The stable API of :mod:`traffictwin.trainer` in one namespace (see its docstring): importing
this module imports Lightning; the package loads it on first use."""

from traffictwin.model_format import (  # noqa: F401 - re-exported: the one checkpoint format
    CKPT_SHA_KEY,
    MODEL_FORMAT,
    CheckpointError,
    check_model_pair,
    model_checkpoint,
    net_state_dict,
    read_model_checkpoint,
    read_model_meta,
    save_model_checkpoint,
    save_model_files,
)
from traffictwin.trainer.callbacks import (  # noqa: F401
    FiniteGuard,
    History,
    TrainingDiverged,
    best_checkpoint,
    early_stopping,
)
from traffictwin.trainer.fit import (  # noqa: F401
    BEST_DIR,
    FitLoop,
    Fitted,
    NetModule,
    RunRecord,
    fit_and_publish,
    fit_run,
)
from traffictwin.trainer.publish import (  # noqa: F401
    FitResult,
    ModelOutputs,
    fit_metrics,
    fit_result,
    log_fitted_model,
    publish,
    stopped_early,
)
from traffictwin.trainer.sampling import RankShardSampler, rank_layout  # noqa: F401
from traffictwin.trainer.settings import (  # noqa: F401
    ACCELERATORS,
    PRECISIONS,
    TrainerSettings,
    build_trainer,
    check_device,
    native_bf16_cpu,
    resolve_precision,
    seed_everything,
)
from traffictwin.trainer.tracking import (  # noqa: F401
    TrackingSettings,
    global_rank,
    log_checkpoint,
    log_final_metrics,
    log_model,
    mlflow_logger,
    tracked_run,
)
