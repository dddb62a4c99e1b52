"""The Markdown summary of the WPSE experiment's ``results.json`` (``table.md``)."""


def results_table(results: dict) -> str:
    """``table.md`` of a WPSE experiment: the held-out errors per method and budget, locality,
    the widths, the oracle sweep, the timing rows (when ``results`` has them), few edits,
    temporal smoothness, reuse, overshoot and layering, from ``results.json``'s keys."""
    lines = _errors(results)
    if "timing" in results:
        lines += _timing(results["timing"])
    lines += _few_edits(results["few_edits"], results["new_width"])
    lines += _probes(results)
    return "\n".join(lines) + "\n"


def _errors(results: dict) -> list[str]:
    budgets = list(next(iter(results["errors"].values())))
    lines = [
        "| method | "
        + " | ".join(f"P={b.removeprefix('p')} mean / p95 / max (mm)" for b in budgets)
        + " |",
        "|---|" + "---|" * len(budgets),
    ]
    for method, by_budget in results["errors"].items():
        cells = [
            "{mean_mm:.3f} / {p95_mm:.3f} / {max_mm:.2f}".format(**by_budget[b]) for b in budgets
        ]
        lines.append(f"| {method} | " + " | ".join(cells) + " |")
    loc = results["locality"]
    lines += [
        "",
        f"Locality (eye weights changed at {loc['probes']} probes of edited poses, "
        f"{loc['region_vertices']} mouth vertices): PSE keeps {loc['pse_retained']:.1%}, "
        f"WPSE keeps {loc['wpse_retained']:.1%} of the mouth correction "
        f"(the nonlinear blend itself: {loc['desired_retained']:.1%}).",
        "",
        "| model | LOO sigma | GUI value | LOO RMS (mm) | max correction at rest pose (mm) |",
        "|---|---|---|---|---|",
    ]
    for key, s in results["sigma"].items():
        rest = results["max_correction_at_rest_pose_mm"][key]
        lines.append(
            f"| {key} | {s['loo_sigma']:.4f} | {s['gui_value']:.3f} | {s['loo_rms_mm']:.3f} "
            f"| {rest:.2f} |"
        )
    lines += ["", "Held-out mean error (mm) against sigma (oracle sweep, for reference):"]
    for key, points in results["sigma_sweep_held_out_mean_mm"].items():
        lines.append(f"- {key}: " + ", ".join(f"{s:.3f}: {e:.4f}" for s, e in points))
    return lines


def _timing(rows: list[dict]) -> list[str]:
    lines = [
        "",
        "| part | vertices (edited) | edits | train (s) | run time median / min (ms/frame) "
        "| vmap over the take (ms/frame) | NumPy (ms/frame) | rig evaluate (ms) "
        "| load average |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        lines.append(
            f"| {row['part']} | {row['vertices']} ({row['edited_vertices']}) | {row['edits']} | "
            f"{row['train_s']:.2f} | {row['runtime_ms']:.2f} / {row['runtime_min_ms']:.2f} | "
            f"{row['batched_runtime_ms']:.2f} | "
            f"{row['numpy_runtime_ms']:.2f} | {row['rig_evaluate_ms']:.2f} | "
            f"{row['load_average_1min']:.1f} |"
        )
    return lines


def _few_edits(few: dict, new_width: dict) -> list[str]:
    methods = list(next(iter(few.values())))
    lines = [
        "",
        "Few edits (held-out mean / p95 mm; LOO width for pse and wpse, the one-standard-error "
        "width for wpse_new_width):",
        "",
        "| method | " + " | ".join(f"P={p}" for p in few) + " |",
        "|---|" + "---|" * len(few),
    ]
    for method in methods:
        cells = ["{mean_mm:.3f} / {p95_mm:.3f}".format(**few[p][method]) for p in few]
        lines.append(f"| {method} | " + " | ".join(cells) + " |")
    lines += [
        "",
        "| model | one-SE sigma | LOO-min sigma | SE (mm) | fit (s) |",
        "|---|---|---|---|---|",
    ]
    for key, w in new_width.items():
        lines.append(
            f"| {key} | {w['sigma']:.4f} | {w['loo_min_sigma']:.4f} | "
            f"{w['standard_error_mm']:.3f} | {w['fit_seconds']:.1f} |"
        )
    return lines


def _probes(results: dict) -> list[str]:
    tem, reu = results["temporal"], results["reuse"]
    lines = [
        "",
        f"Temporal (one edit at Live Link frame {tem['edited_frame']}, sigma {tem['sigma']:.3f}): "
        f"correction max step {tem['max_step_mm']:.3f} mm/frame, max acceleration "
        f"{tem['max_acceleration_mm']:.3f} mm/frame^2; the take itself: step "
        f"{tem['take_max_step_mm']:.3f}, acceleration {tem['take_max_acceleration_mm']:.3f}.",
        "",
        f"Reuse (library of {len(reu['library_frames'])} edits from the first half, mouth ROI, "
        f"tau {reu['tau']:.1f}): second-half mean error {reu['error_before_mm']:.3f} -> "
        f"{reu['error_after_mm']:.3f} mm (ROI {reu['error_before_roi_mm']:.3f} -> "
        f"{reu['error_after_roi_mm']:.3f}; edits found at "
        f"{reu['frames_with_edits_found']} of "
        f"{reu['query_frames'][1] - reu['query_frames'][0] + 1} "
        f"frames); tau x0.5: {reu['tau_x0.5']['error_after_mm']:.3f}, "
        f"tau x1.5: {reu['tau_x1.5']['error_after_mm']:.3f} mm.",
    ]
    over = results["overshoot"]["max_correction_mm"]
    lines += ["", f"Overshoot, pair {' + '.join(results['overshoot']['pair'])} (max mm):"]
    lines += [
        f"- {k}: " + ", ".join(f"{t} {value:.2f}" for t, value in v.items())
        for k, v in over.items()
    ]
    lay = results["layering"]
    lines += [
        "",
        f"Layering (two edits {lay['pose_distance']:.3f} apart, sigma {lay['sigma']:.3f}, "
        f"layer sigma {lay['layer_sigma']:.3f}; max mm):",
    ]
    for name in ("single_layer", "layered"):
        r = lay[name]
        lines.append(
            f"- {name}: edit a {r['edit_a_max_mm']:.3f}, edit b {r['edit_b_max_mm']:.3f}, "
            f"between {r['between_max_mm']:.3f}, max correction on the line "
            f"{r['max_correction_on_line_mm']:.2f}"
        )
    return lines
