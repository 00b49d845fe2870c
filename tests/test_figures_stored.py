"""Figures drawn from stored tables equal the figures of the recomputed results (assets_lib/stages/figures.py)."""

from __future__ import annotations


def test_allan_figure_from_the_stored_tables_is_the_recomputed_one():
    """The Allan plot rebuilt from the stage's stored ``allan`` and ``noise`` tables is byte-identical to the plot
    of the in-memory curves and fits ``allan_tables`` computes; a channel whose rows cannot determine the drawn
    model is reported as such (None), not guessed."""
    from assets_lib.noise.identification import plot_allan
    from assets_lib.sim.simulator import example_device, simulate_run
    from assets_lib.stages.figures import StoredCurve, stored_noise_model
    from assets_lib.stages.noise import allan_tables
    from raw_schemas.readers import ingest_frames
    from raw_schemas.tables import GYRO_COLUMNS

    dev = example_device("FIG-000", "tactical", seed=3)
    sim = simulate_run(dev.for_power_cycle(0, 3), "static_long", "pc00-static", seed=3, table_log=False,
                       plan_kwargs={"static_duration_s": 900.0})
    ing = ingest_frames(sim.manifest, sim.imu_raw, sim.table_raw)
    meta = {"sample_rate_hz": ing.manifest.sample_rate_hz, "run_id": ing.manifest.run_id, "power_cycle_index": 0}
    tables, _, _, results, fits = allan_tables("FIG-000__pc00-static", ing.imu, meta)
    allan, noise = tables["allan"], tables["noise"]
    cols = ("tau_s", "adev", "ci_lo", "ci_hi")
    curves = {c: StoredCurve(c, str(a.kind.iloc[0]), *(a[k].to_numpy(float) for k in cols))
              for c, a in ((c, allan[allan.channel == c]) for c in GYRO_COLUMNS)}
    models = {c: stored_noise_model(noise[noise.channel == c]) for c in GYRO_COLUMNS}
    assert all(m is not None for m in models.values())
    assert plot_allan(curves, models, title="t") == plot_allan({c: results[c] for c in GYRO_COLUMNS},
                                                                {c: fits[c] for c in GYRO_COLUMNS}, title="t")
    # every term a bound: the stored values (NaN) do not say what the fit kept, so no model is rebuilt
    rows = noise[noise.channel == GYRO_COLUMNS[0]].copy()
    rows["is_upper_bound"] = True
    assert stored_noise_model(rows) is None
