"""Stage ``sim_to_real`` (group ``diagnosis``): per device, the sim-to-real gap diagnosis of all its ingested runs
(``assets_lib.simreal``): where the real data differ from the fitted twin, which unmodelled effect explains it, how far
the gap shrinks. Stores the report JSON, the HTML report and the augmented twin as files, the ranked views and the
accepted effects as tables, the where-map and before/after plots."""

from __future__ import annotations

import json

import pandas as pd

from assets_lib.simreal.diagnose import diagnose_device
from assets_lib.simreal.experiment import experiment_from_frames
from assets_lib.simreal.report import _clean, plots, render_html
from assets_lib.simreal.tablefree_diagnose import diagnose_tablefree
from assets_lib.stages.spec import StageOutput, stage
from raw_schemas.manifest import Manifest

#: replicates per device in the pipeline (keeps ``imulab run`` on the default archive short; ``imulab diagnose
#: --replicates`` for more); fixed seed: the stage is deterministic
STAGE_REPLICATES = 5
STAGE_SEED = 0
#: test kinds the twin can replay (plans with known orientations), and those that give plateau residuals
TWIN_KINDS = ("rate", "multiposition", "tumble", "static")
CALIBRATION_KINDS = ("rate", "multiposition", "tumble")
#: verdicts the asset check warns about
WARN_VERDICTS = ("unexplained", "partly_explained", "noise_model")


@stage("sim_to_real", level="device", group="diagnosis", code_version="1", upstream=["ingested_run"])
def sim_to_real(device: str, inputs) -> StageOutput | None:
    """Sim-to-real gap diagnosis of one device (where / which effect / how far it shrinks), docs/simreal.md."""
    frames, tablefree = [], []
    for k in inputs.keys_of("ingested_run"):
        m = Manifest.model_validate_json(inputs.file("ingested_run", "manifest.json", key=k))
        if m.test_kind not in TWIN_KINDS and m.test_kind != "tablefree":
            continue
        imu = inputs.table("ingested_run", "imu", key=k)
        table = inputs.table("ingested_run", "table", key=k) if inputs.has_table("ingested_run", "table", key=k) else None
        (tablefree if m.test_kind == "tablefree" else frames).append((m, imu, table))
    if any(m.test_kind in CALIBRATION_KINDS for m, _, _ in frames):
        exp = experiment_from_frames(frames)  # table runs: the plan twin (hand-moved runs of the device left out)
        diag = diagnose_device(None, device, replicates=STAGE_REPLICATES, seed=STAGE_SEED, workers=1, experiment=exp)
    elif tablefree and not frames:  # hand-moved sessions only: the table-free experiment
        diag = diagnose_tablefree(tablefree, device, replicates=STAGE_REPLICATES, seed=STAGE_SEED, workers=1)
    else:
        return None  # not applicable: no calibration run to compare the twin with
    rep = _clean(diag.report)
    figs = plots(diag)
    import base64

    pngs = {k: base64.b64decode(v) for k, v in figs.items() if k in ("where", "before_after")}
    for i, v in enumerate((diag.plots.get("extra_png") or {}).values()):
        pngs[f"tablefree_{i}"] = base64.b64decode(v)
    where = pd.DataFrame(rep["where"], columns=["view", "run_id", "channel", "step_index", "z", "q_value"])
    where["step_index"] = where["step_index"].astype("Int64")
    effects = pd.DataFrame(rep["effects"], columns=["family", "channel", "magnitude", "ci_lo", "ci_hi", "unit",
                                                    "delta_lpd", "folds_positive", "folds"])
    return StageOutput(
        tables={"where": where, "effects": effects},
        meta={"verdict": rep["verdict"], "gap": rep["gap"], "shrink": rep["shrink"], "ambiguity": rep["ambiguity"],
              "replicates": STAGE_REPLICATES, "seed": STAGE_SEED},
        files={f"{device}.json": (json.dumps(rep, indent=1) + "\n").encode(),
               f"{device}.html": render_html(rep, diag).encode(),
               f"{device}.twin.json": (json.dumps(_clean(diag.augmented.to_json()), indent=1) + "\n").encode()},
        summary={"verdict": rep["verdict"], "gap_z": float(rep["gap"]["z"]), "n_effects": len(rep["effects"]),
                 "shrink_ratio": float(rep["shrink"]["ratio"] or 0.0)},
        plots=pngs,
    )
