"""`etam bench`: every benchmark of the suite, with results as plain data."""

from __future__ import annotations

import platform
import time
from collections.abc import Callable

import psutil

from benchmarks import (dashboard, filters, latency, mapping, mosaic, odometry, playback, readers, tracking, transport,
                        usb, writers)


def _simulator(quick: bool) -> list[dict]:
    """The built-in simulator, scene by scene as the live source runs it (both cameras of stereo):
    events generated per second, and real-time factor (below 1: a live stream lags)."""
    from services.camera.sources import open_sources

    rows = []
    for scene, seconds in (("objects", 4.0), ("rotation", 0.5), ("6dof", 2.0), ("stereo", 1.0)):
        duration_us = int(seconds * 1e6 / (4 if quick else 1))
        cameras = open_sources(f"sim:{scene}")
        for cam in cameras:
            cam.advance(1_000)  # kernels compiled before timing
        t0 = time.perf_counter()
        n = sum(len(cam.advance(duration_us)) for cam in cameras)
        wall = time.perf_counter() - t0
        rows.append({"stage": f"camera.simulator.{scene}", "events": n, "events_per_s": n / wall,
                     "realtime_factor": (duration_us - 1_000) / 1e6 / wall})
    return rows


BENCHMARKS: dict[str, Callable[[bool], list[dict]]] = {
    "transport": lambda quick: transport.run(duration_s=1.0 if quick else 3.0, peer_packets=50 if quick else 300),
    "readers": readers.run,
    "filters": filters.run,
    "writers": writers.run,
    "playback": playback.run,
    "tracker": tracking.speed,
    "tracking": tracking.run,
    "tracking-held-out": tracking.held_out,
    "mapping": mapping.run,
    "mosaic": mosaic.run,
    "odometry": odometry.run,
    "latency": latency.run,
    "simulator": _simulator,
    "usb": usb.run,
    "dashboard": dashboard.run,
}


def run(quick: bool = False, only: list[str] | None = None) -> dict:
    """Run the chosen benchmarks; a dict with the machine and each benchmark's rows."""
    unknown = set(only or []) - set(BENCHMARKS)
    if unknown:
        raise ValueError(f"unknown benchmark(s) {', '.join(sorted(unknown))}; known: {', '.join(BENCHMARKS)}")
    results = {"machine": {"cpu": platform.processor() or platform.machine(), "cores": psutil.cpu_count(),
                           "python": platform.python_version()}}
    for name, bench in BENCHMARKS.items():
        if not only or name in only:
            results[name] = bench(quick)
    return results


def format_results(results: dict) -> str:
    """A human-readable table per benchmark."""
    lines = [f"machine: {results['machine']}"]
    for row in results.get("transport", []):
        offered = row["offered_events_per_s"]
        offered = "  max" if offered == "max" else f"{offered / 1e6:5.1f}"
        lines.append(
            f"transport  offered {offered} Mev/s "
            f"({row['events_per_packet']} ev/packet): {row['messages_per_s']:7.0f} msg/s "
            f"{row['events_per_s'] / 1e6:6.2f} Mev/s delivered, lost {row['lost_messages']}, "
            f"latency p50 {row['latency_p50_ms']:.2f} ms p99 {row['latency_p99_ms']:.2f} ms")
        if "ratio" in row:
            lines.append(
                f"  beside dv-processing: NetworkWriter -> NetworkReader {row['peer_events_per_s'] / 1e6:.1f} Mev/s "
                f"(complete: {row['peer_complete']}), ratio {row['ratio']:.2f}; numpy -> packet ETAM "
                f"{row['etam_ingest_events_per_s'] / 1e6:.0f} Mev/s, -> EventStore "
                f"{row['peer_ingest_events_per_s'] / 1e6:.2f} Mev/s, ratio {row['ingest_ratio']:.0f}")
        elif row.get("peer_error"):
            lines.append(f"  dv-processing: {row['peer_error']}")
    for row in results.get("readers", []):
        peer = (f"{row['peer_events_per_s'] / 1e6:6.1f} Mev/s, ratio {row['ratio']:.2f}" if row["ratio"]
                else row["peer_error"])
        lines.append(f"{row['stage']:<22} ETAM {row['etam_events_per_s'] / 1e6:6.1f} Mev/s | {row['peer']:<13} {peer}"
                     f"  ({row['events']} events, {row['bytes_per_event']:.1f} B/event)")
    for row in results.get("filters", []):
        peer = (f"{row['peer_events_per_s'] / 1e6:6.1f} Mev/s, ratio {row['ratio']:.2f}; keeps "
                f"{row['peer_signal_kept']:.1%} of signal, {row['peer_noise_kept']:.1%} of noise" if row["ratio"]
                else row["peer_error"])
        lines.append(f"{row['stage']}: ETAM {row['etam_events_per_s'] / 1e6:6.1f} Mev/s, keeps "
                     f"{row['etam_signal_kept']:.1%} of signal, {row['etam_noise_kept']:.1%} of noise | {row['peer']} "
                     f"{peer}  ({row['events']} events, {row['noise_fraction']:.0%} noise)")
    for row in results.get("writers", []):
        peer = (f"{row['peer_events_per_s'] / 1e6:6.1f} Mev/s at {row['peer_bytes_per_event']:.2f} B/event, "
                f"ratio {row['ratio']:.2f}" if row["ratio"] else row["peer_error"])
        lines.append(f"{row['stage']:<26} ETAM {row['etam_events_per_s'] / 1e6:6.1f} Mev/s at "
                     f"{row['etam_bytes_per_event']:.2f} B/event | {row['peer']} {peer}")
    for row in results.get("playback", []):
        if "error" in row:
            lines.append(f"{row['stage']}: {row['error']}")
            continue
        lines.append(f"{row['stage']}: median {row['events_per_s'] / 1e6:.1f} Mev/s (worst "
                     f"{row['worst_events_per_s'] / 1e6:.1f}, best {row['best_events_per_s'] / 1e6:.1f}) over "
                     f"{row['plays']} plays of {row['file_events']} events; received {row['events']}, "
                     f"{row['seq_gaps']} sequence gaps")
    for row in results.get("tracking", []) + results.get("tracking-held-out", []):
        lines.append(f"{row['stage']} seed {row['seed']!s:>4} ({row['duration_s']:g} s): OP50 {row['op50']:.3f} "
                     f"OP75 {row['op75']:.3f} AUC {row['success_auc']:.3f} P@20 {row['precision20']:.3f} "
                     f"FP/s {row['false_positives_per_s']:.2f} IDsw/obj/min {row['id_switches_per_object_minute']:.2f} "
                     f"IDF1 {row['idf1']:.3f} MOTA {row['mota']:.3f}  ({row['method']})")
        if "id_switches_crossing" in row:  # where the errors are (means only)
            split = " ".join(f"{k} {v:.3f}" if v is not None else f"{k} -" for k, v in (
                ("crossing", row["precision20_crossing"]), ("clear", row["precision20_clear"])))
            lines.append(f"{'':<26} IDsw/obj/min at crossings {row['id_switches_crossing']:.2f}, on return "
                         f"{row['id_switches_return']:.2f}, other {row['id_switches_other']:.2f}; P@20 {split}")
    for row in results.get("tracker", []):
        p99 = f", p99 {row['update_ms_p99']:.2f}" if "update_ms_p99" in row else ""
        lines.append(f"{row['stage']} {row['method']:<20} {row['window_ms']:.0f} ms windows: "
                     f"{row['events_per_s'] / 1e6:6.2f} Mev/s, update p50 {row['update_ms_p50']:.3f} ms{p99}"
                     f"  (stream {row['stream_events_per_s'] / 1e6:.2f} Mev/s)")
    for row in results.get("latency", []):
        rig = "etam up" if row["web"] else "etam up --no-web"
        if "error" in row:
            lines.append(f"{row['stage']} ({rig}): {row['error']}")
            continue
        lines.append(f"tracking latency camera publish -> tracks publish, {rig}: p50 {row['latency_ms_p50']:.2f} ms "
                     f"p99 {row['latency_ms_p99']:.2f} ms max {row['latency_ms_max']:.1f} ms over {row['updates']} "
                     f"updates at {row['events_per_s'] / 1e6:.2f} Mev/s")
    for row in results.get("mapping", []):
        if row["stage"] == "mapping live":
            lines.append(f"{row['stage']} ({row['scene']}, {row['method']}, {row['events_per_s'] / 1e6:.2f} Mev/s): "
                         + (row["error"] if "error" in row else
                            f"pending at most {row['pending_events_max']} events, lag p50 {row['lag_ms_p50']:.0f} ms "
                            f"max {row['lag_ms_max']:.0f} ms, dropped {row['dropped_events']}, {row['keyframes']} "
                            f"keyframes, done {row['drain_s']} s after the file"
                            + (f", stereo frames skipped {row['stereo_frames_skipped']} of {row['stereo_frames']}"
                               if row.get("stereo_frames") else f", sweep stride {row.get('sweep_stride')}")))
        elif "events_per_s" in row:
            lines.append(f"{row['stage']}: {row['events_per_s'] / 1e6:.2f} Mev/s ({row['planes']} planes, "
                         f"{row['size']}, {row['threads']} threads)")
        else:
            lines.append(f"{row['stage']} {row['scene']:>6} seed {row['seed']!s:>9}: median error "
                         f"{row['median_error_pct_of_range']:.2f} % of range, "
                         f"mean {row['mean_relative_error_pct']:.2f} % "
                         f"of depth, {row['mean_abs_error_m'] * 100:.1f} cm, within 5 % {row['within_5pct']:.3f}, "
                         f"completeness {row['completeness']:.2f}, {row['points']:.0f} points")
    for row in results.get("mosaic", []):
        if row["stage"] == "mosaic quality":
            lines.append(f"{row['stage']} seed {row['seed']!s:>9}: PSNR {row['psnr_db']:.2f} dB, "
                         f"SSIM {row['ssim']:.3f}, observed {row['observed']:.1%} of the panorama (Poisson alone: "
                         f"{row['poisson_psnr_db']:.2f} dB, SSIM {row['poisson_ssim']:.3f})")
        elif "events_per_s" in row:
            lines.append(f"{row['stage']}: {row['events_per_s'] / 1e6:.2f} Mev/s on one core ({row['size']})")
        else:
            lines.append(f"{row['stage']} {row['size']}: {row['s_per_image'] * 1e3:.0f} ms per image "
                         f"({row['pairs']} event pairs)")
    for row in results.get("odometry", []):
        if row["stage"] == "odometry rotation speed":
            lines.append(f"{row['stage']} ({'panoramic map' if row['panorama'] else 'integration alone'}): "
                         f"{row['estimates_per_s']:.0f} estimates per CPU second, {row['ms_per_estimate']:.2f} ms "
                         f"each, {row['realtime_factor']:.1f}x real time on a {row['stream_events_per_s'] / 1e6:.2f} "
                         f"Mev/s stream, one core ({row['wall_estimates_per_s']:.0f}/s of wall-clock time)")
        elif row["stage"] == "odometry 6dof speed":
            lines.append(f"{row['stage']}: {row['updates_per_s']:.0f} updates per CPU second, "
                         f"{row['ms_per_update']:.2f} ms each, {row['realtime_factor']:.1f}x real time on a "
                         f"{row['stream_events_per_s'] / 1e6:.2f} Mev/s stream, one core, "
                         f"{row['map_points']} map points")
        elif row["stage"] in ("odometry 6dof", "odometry 6dof stereo"):
            lines.append(f"{row['stage']} seed {row['seed']!s:>9}: ATE {row['ate_m'] * 100:.1f} cm = "
                         f"{row['ate_percent_of_distance']:.2f} % of {row['distance_m']:.2f} m (SE(3)-aligned "
                         f"{row['se3_ate_percent']:.2f} %, Sim(3) {row['sim3_ate_percent']:.2f} %), orientation RMS "
                         f"{row['ate_rot_deg']:.2f} deg, RPE "
                         + (f"{row['rpe_deg_per_s']:.2f} deg/s {row['rpe_cm_per_s']:.1f} cm/s" if "rpe_deg_per_s" in row
                            else "none (under a second of poses)")
                         + f", {row['lost']:.0f} updates lost, {row['keyframes']:.0f} keyframes; without the IMU "
                         f"{row['no_imu_ate_percent']:.2f} %, {row['no_imu_lost']:.0f} lost")
            if "live_ate_m" in row:
                lines.append(f"{'':>{len(row['stage']) + 16}}live: own poses from {row['live_started_s']:.2f} s, "
                             f"{row['live_poses']:.0f} of them, {row['live_lost']:.0f} updates lost, ATE "
                             f"{row['live_ate_m'] * 100:.1f} cm = {row['live_ate_percent']:.2f} % (SE(3) "
                             f"{row['live_se3_ate_percent']:.2f} %), angular velocity RMS "
                             f"{row['live_omega_rms_deg_s']:.1f} deg/s, {row['live_map_parts']:.0f} map parts")
            elif "live_error" in row:
                lines.append(f"{'':>{len(row['stage']) + 16}}live: {row['live_error']}")
        else:
            lines.append(f"{row['stage']} seed {row['seed']!s:>9}: angular velocity RMS {row['omega_rms_deg_s']:.1f} "
                         f"deg/s = {row['omega_rms_of_peak']:.2%} of the {row['omega_peak_deg_s']:.0f} deg/s peak, "
                         f"orientation error at the end {row['final_rot_err_deg']:.2f} deg (RMS "
                         f"{row['ate_rot_deg']:.2f}), RPE {row['rpe_deg_per_s']:.2f} deg/s; integration alone: "
                         f"{row['integrated_final_rot_err_deg']:.2f} deg at the end")
    for row in results.get("usb", []):
        lines.append(f"usb decode {row['model']:>9}: {row['events_per_s'] / 1e6:6.1f} Mev/s on one core "
                     f"({row['mb_per_s']:.0f} MB/s, {row['bytes_per_event']:.2f} bytes an event, "
                     f"{row['events']} events)")
    for row in results.get("dashboard", []):
        if "error" in row:
            lines.append(f"{row['stage']} ({row['source']}): {row['error']}")
            continue
        lines.append(f"{row['stage']} ({row['source']}), {row['clients']} client(s): "
                     f"{row['cpu_percent_of_core']:.1f} % of a core, event image "
                     f"{row['image_updates_per_s']:.1f} updates/s at the slowest client "
                     f"({row['frames_per_s']:.1f}/s sent), {row['points_shown']} points shown, "
                     f"{row['client_mb_per_s']:.2f} MB/s to each client, machine "
                     f"{row['machine_cpu_percent']:.0f} % busy")
    for row in results.get("simulator", []):
        lines.append(f"{row['stage']:<26} {row['events_per_s'] / 1e6:6.2f} Mev/s, "
                     f"{row['realtime_factor']:.1f}x real time")
    return "\n".join(lines)
