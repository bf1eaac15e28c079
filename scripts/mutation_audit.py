"""Does the suite catch the bugs users would hit? Each mutation below is applied alone to a scratch
copy of the committed tree (`git archive HEAD`), the tests named for it are run there, and the
mutation counts as caught when at least one of them fails. Nothing in the checkout is modified.

    .venv/bin/python scripts/mutation_audit.py            # all mutations (~15 min on 2 cores)
    .venv/bin/python scripts/mutation_audit.py 1 4        # some of them

Each is a one-line bug a developer could plausibly make, in I/O, calibration, geometry, the
solver, export, the runtime, resume, evaluation, the synthetic world or the bench;
docs/testing.md lists which test catches each.
"""

from __future__ import annotations

import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


@dataclass(frozen=True)
class Mutation:
    name: str
    file: str  # relative to the root; "" for a mutation made by `script`
    old: str
    new: str
    tests: tuple[str, ...]
    script: str = ""  # python run in the scratch copy instead of a text replacement


UNTRAINED = """
import torch
from models.checkpoint import load_checkpoint, save_checkpoint
from models.d3lvo import D3LVO
from export.onnx_export import ExportConfig, export_checkpoint
cfg = load_checkpoint('d3lvo_deploy/default_model/default.pt')['config']
torch.manual_seed(0)
save_checkpoint('d3lvo_deploy/default_model/default.pt', D3LVO(cfg).eval(), cfg, step=1000)
export_checkpoint('d3lvo_deploy/default_model/default.pt', ExportConfig(out='d3lvo_deploy/default_model'))
"""

MUTATIONS = [
    Mutation("frames t-1 and t swapped in the flow+pose export wrapper", "export/stages.py",
             'self.model.flow_pose(levels("feat1"), levels("feat2")', 'self.model.flow_pose(levels("feat2"), levels("feat1")',
             ("tests/test_export.py::test_parity_reduced_size", "tests/test_runtime.py::test_onnx_trajectory_equals_torch")),
    Mutation("change_frame dropped in Odometry.step (poses left in cam2)", "d3lvo_deploy/odometry.py",
             "self.relative = change_frame(A2, self.calib.T_cam0_cam2)", "self.relative = A2",
             ("tests/test_runtime.py::test_onnx_trajectory_equals_torch",)),
    Mutation("an untrained network shipped as the bundled model", "", "", "",
             ("tests/test_default_model.py", "tests/test_confidence.py"), script=UNTRAINED),
    Mutation("INT8 calibrated on RGB scaled by 1e-3 (activation ranges at the wrong scale)", "export/quantize.py",
             "            rgb = pre.rgb_input(seq.image(i))", "            rgb = 1e-3 * pre.rgb_input(seq.image(i))",
             ("tests/test_export.py::test_reduced_precision_exports",)),
    Mutation("training --resume that discards weights, loss balance and optimizer state", "models/train.py",
             '        model.load_state_dict(ck["model"])\n        criterion.load_state_dict(ck["loss"])\n'
             '        try:\n            opt.load_state_dict(ck["optimizer"])',
             '        try:\n            pass',
             ("tests/test_training.py::test_resume_equals_an_uninterrupted_run",)),
    Mutation("the synthetic renderer moves the camera 1.2x the motion written to poses.txt",
             "d3lvo_deploy/synth/generator.py", "    scene = make_scene(poses, cfg.seed)\n",
             "    scene = make_scene(poses, cfg.seed)\n    poses = poses.copy()\n    poses[:, :3, 3] *= 1.2\n",
             ("tests/test_synth.py",)),
    Mutation("the pose head ignores its input (returns its start pose: a constant motion model)",
             "models/pose_gn.py", "K / scale, self.cfg.gn_iters, self.cfg.gn_huber,", "K / scale, 0, self.cfg.gn_huber,",
             ("tests/test_training.py::test_short_training_beats_the_baselines",)),
    Mutation("pyrDown levels given an area-resize principal point (x -> (x + 0.5) / 2 - 0.5)", "d3lvo_deploy/direct.py",
             "    Kl[:2] *= 0.5 ** level\n", "    Kl[:2] *= 0.5 ** level\n    Kl[:2, 2] += 0.5 * 0.5 ** level - 0.5\n",
             ("tests/test_direct.py",)),
    Mutation("direct tracker's Huber threshold fixed instead of following the residuals", "d3lvo_deploy/direct.py",
             "    return max(HUBER_K * MAD_TO_SIGMA * float(np.median(np.abs(r))), 1e-6)", "    return 0.02",
             ("tests/test_direct.py",)),
    Mutation("direct tracker's rotation Jacobian with the wrong sign", "d3lvo_deploy/direct.py",
             "J = np.concatenate([a, np.cross(Xt, a)], 1)", "J = np.concatenate([a, np.cross(a, Xt)], 1)",
             ("tests/test_direct.py",)),
    Mutation("image_2's baseline applied with the wrong sign", "d3lvo_deploy/calib.py",
             "        return make_se3(np.eye(3), b)", "        return make_se3(np.eye(3), -b)",
             ("tests/test_direct.py", "tests/test_calib.py", "tests/test_runtime.py::test_streaming_api_matches_the_file")),
    Mutation("poses composed in the wrong order in Odometry.step", "d3lvo_deploy/odometry.py",
             "before, self.pose = self.pose, self.pose @ self.relative",
             "before, self.pose = self.pose, self.relative @ self.pose",
             ("tests/test_runtime.py::test_streaming_api_matches_the_file",)),
    Mutation("only the encoder's file checked against the manifest's hash", "d3lvo_deploy/manifest.py",
             'if verify_hashes and sha256_file(f) != entry["sha256"]:',
             'if verify_hashes and label == "encoder" and sha256_file(f) != entry["sha256"]:',
             ("tests/test_export.py::test_tampered_and_mismatched",)),
    Mutation("bench reports the mean as the median", "d3lvo_deploy/bench.py",
             '"median": float(np.median(a))', '"median": float(np.mean(a))',
             ("tests/test_bench.py::test_stage_times_summary_by_hand",)),
    Mutation("a resumed frame range primes the frame counted from 0, not from --start", "d3lvo_deploy/pipeline.py",
             "            k = rc.start + len(done) - 1", "            k = len(done) - 1",
             ("tests/test_runtime.py::test_frame_range_and_tum",)),
    Mutation("an estimate starting late is scored against GT anchored at frame 0", "d3lvo_deploy/evaluation.py",
             "    gt_rel = relative(gt_poses[first], gt_poses)", "    gt_rel = relative(gt_poses[0], gt_poses)",
             ("tests/test_metrics.py",)),
    Mutation("the true flow ignores the vehicles' own motion", "d3lvo_deploy/synth/generator.py",
             "Xw = point_motion(vehicles, owner.reshape(-1), Xw, frame, frame + 1)",
             "Xw = point_motion(vehicles, owner.reshape(-1), Xw, frame, frame)",
             ("tests/test_traffic.py",)),
    Mutation("the LiDAR sees the vehicles where they are one frame later than the camera does",
             "d3lvo_deploy/synth/generator.py",
             "            scan = scan_lidar(frame_scene, ",
             "            scan = scan_lidar((lambda w: Scene(RayCaster(w['vertices'], w['faces']), w, scene.style, "
             "scene.tex, scene.sun))(world_at(scene.world, vehicles, min(i + 1, cfg.frames - 1))[0]) "
             "if vehicles else frame_scene, ",
             ("tests/test_traffic.py",)),
    Mutation("the LiDAR projection drops P2's fourth column (image_2's baseline)", "d3lvo_deploy/calib.py",
             "        return self.P2 @ self.Tr", "        return np.hstack([self.P2[:, :3], np.zeros((3, 1))]) @ self.Tr",
             ("tests/test_projection.py", "tests/test_frames.py", "tests/test_calib.py",
              "tests/test_runtime.py::test_onnx_trajectory_equals_torch")),
    Mutation("DDP leaves the loss balance terms' gradients out of the all-reduce", "models/train.py",
             "                            dist.all_reduce(q.grad)\n                            q.grad /= world\n",
             "                            pass\n",
             ("tests/test_training.py::test_ddp_replicas_stay_identical_with_clipping_and_equal_one_process",)),
    Mutation("point solver: pyramid levels keep the full-resolution intrinsics", "models/point_solver.py",
             "        Kl = K * (0.5 ** lvl)", "        Kl = K",
             ("tests/test_point_solver.py",)),
    Mutation("point list: padding marked as points", "d3lvo_deploy/points.py",
             "    mask[0, : len(X)] = 1.0", "    mask[0, :] = 1.0",
             ("tests/test_point_solver.py",)),
    Mutation("point solver's median: the upper middle value alone for an even count", "models/point_solver.py",
             "literal([-1.0, 0.0], a)) * 0.5)", "literal([0.0, 0.0], a)) * 0.5)",
             ("tests/test_point_solver.py",)),
    Mutation("runtime hands the solver frame t's points instead of frame t-1's", "d3lvo_deploy/odometry.py",
             "feeds = solver_feeds(prev, solver, self.calib.K2",
             "feeds = solver_feeds(solver, prev, self.calib.K2",
             ("tests/test_point_solver.py",)),
    Mutation("bags: an image paired with the nearest scan however far apart in time",
             "d3lvo_deploy/datasets/rosbag.py", "if back == i and abs(cloud_t[j] - t) <= max_dt:",
             "if back == i:", ("tests/test_formats.py::test_pairing_by_nearest_stamp_by_hand",
                                   "tests/test_formats.py::test_bad_bags_fail_in_one_line_and_write_nothing")),
    Mutation("bags: a /tf_static transform taken the wrong way round (child to parent)",
             "d3lvo_deploy/datasets/rosbag.py", "edges.setdefault(p, []).append((c, T))",
             "edges.setdefault(p, []).append((c, se3_inv(T)))",
             ("tests/test_formats.py::test_recording_formats_give_the_folder_run_poses",)),
    Mutation("KITTI raw: OXTS angles composed as Rx Ry Rz instead of the devkit's Rz Ry Rx",
             "d3lvo_deploy/datasets/kitti_raw.py", "T = make_se3(Rz @ Ry @ Rx, t)", "T = make_se3(Rx @ Ry @ Rz, t)",
             ("tests/test_formats.py::test_kitti_raw_oxts_ground_truth_by_hand",)),
    Mutation("run --config: the file's values override options given on the command line", "cli/run_cmd.py",
             "        if not given(k):", "        if True:", ("tests/test_formats.py::test_results_folder_holds_the_run_and_its_config_repeats_it",)),
    Mutation("pipeline: the reader thread prepares the frame after next", "d3lvo_deploy/pipeline.py",
             "ahead = pool.submit(load, i + 1)", "ahead = pool.submit(load, min(i + 2, rc.start + n - 1))",
             ("tests/test_runtime.py::test_pipelined_run_writes_the_sequential_poses",)),
    Mutation("auto: an uncompiled OpenVINO held to the cached one's shorter pay-back", "d3lvo_deploy/backends.py",
             "need = AUTO_MIN_FRAMES_CACHED if cached else AUTO_MIN_FRAMES",
             "need = AUTO_MIN_FRAMES_CACHED",
             ("tests/test_backends.py::test_auto_keeps_a_short_run_off_an_uncompiled_openvino",)),
    Mutation("change_frame conjugates the wrong way round (inv(T) A T)", "d3lvo_deploy/geometry.py",
             "return np.asarray(T_b_a) @ np.asarray(T_rel) @ se3_inv(T_b_a)",
             "return se3_inv(T_b_a) @ np.asarray(T_rel) @ np.asarray(T_b_a)",
             ("tests/test_runtime.py::test_onnx_trajectory_equals_torch",)),
    Mutation("network view: the crop two rows taller than the network's aspect", "d3lvo_deploy/projection.py",
             "ch = min(src_height, int(round(cw * net_height / net_width)))",
             "ch = min(src_height, int(round(cw * net_height / net_width)) + 2)",
             ("tests/test_runtime.py::test_onnx_trajectory_equals_torch",)),
    Mutation("depth cache keyed by the frame name alone (a rewritten scan is served stale)", "models/data.py",
             'f = self.cache / f"{self.seq.frame_names[i]}-{kind}-{stamp}.npz"',
             'f = self.cache / f"{self.seq.frame_names[i]}-{kind}.npz"',
             ("tests/test_training.py::test_depth_cache_gives_the_same_samples_and_follows_changed_scans",)),
    Mutation("the one-process sampler draws its own permutation, not DistributedSampler's", "models/train.py",
             "g = torch.Generator().manual_seed(self.seed + self.epoch)",
             "g = torch.Generator().manual_seed(self.seed + self.epoch + 1)",
             ("tests/test_training.py::test_ddp_replicas_stay_identical_with_clipping_and_equal_one_process",)),
    Mutation("export builds the checkpoint's solver, ignoring --set (the manifest still lists --set)",
             "export/onnx_export.py", 'model = build_model({**ck, "config": cfg})', "model = build_model(ck)",
             ("tests/test_point_solver.py::test_export_set_reaches_the_graph",)),
    Mutation("the classical mode takes the model's damping as its stop threshold", "d3lvo_deploy/direct.py",
             'stop_step=model_config["pt_stop"]', 'stop_step=model_config["pt_damping"]',
             ("tests/test_point_solver.py::test_direct_method_is_the_models_classical_mode",)),
    Mutation("the runtime feeds frame t-1's scan to the restart's check", "d3lvo_deploy/points.py",
             'feeds[SCAN_DEPTH_INPUT] = cur.depth[None, None]', 'feeds[SCAN_DEPTH_INPUT] = prev.depth[None, None]',
             ("tests/test_point_solver.py::test_runtime_feeds_frame_ts_own_scan",)),
    Mutation("the classical mode keeps the restart where it fits frame t's scan worse", "d3lvo_deploy/direct.py",
             "            < cfg.restart_depth * lidar_depth_error(", "            > cfg.restart_depth * lidar_depth_error(",
             ("tests/test_point_solver.py::test_restart_depth_is_the_numpy_trackers",)),
    Mutation("shadow_2 marks what a mover shades now, not where the shading changes", "d3lvo_deploy/synth/traffic.py",
             "    out[sel] = now != then", "    out[sel] = now",
             ("tests/test_traffic.py::test_moving_shadow_band_by_hand",
              "tests/test_traffic.py::test_moving_shadows_change_the_image_where_shadow_2_says")),
    Mutation("the confidence's target ignores moving shadows when asked to count them", "models/train.py",
             "    if shadows and \"shadow\" in batch:", "    if False:",
             ("tests/test_targets.py::test_motion_target_counts_moving_shadows_only_when_asked",)),
    Mutation("the solver's graph takes the Huber median over every point whatever the stride", "models/point_solver.py",
             "            k = huber_threshold(nr, ok * median_mask, s.median_stride)",
             "            k = huber_threshold(nr, ok * median_mask)",
             ("tests/test_point_solver.py::test_confidence_one_is_the_numpy_tracker",
              "tests/test_point_solver.py::test_export_set_reaches_the_graph")),
    Mutation("the classical tracker picks the median's points by their place among those in view", "d3lvo_deploy/direct.py",
             "            k = stride_threshold(r, np.flatnonzero(ok) if index is None else index[ok], cfg.median_stride)",
             "            k = stride_threshold(r, np.arange(len(r)) if index is None else index[ok], cfg.median_stride)",
             ("tests/test_point_solver.py::test_confidence_one_is_the_numpy_tracker",)),
    Mutation("frames prepared with numpy's BLAS threads left free", "d3lvo_deploy/odometry.py",
             "        with one_blas_thread():  # no BLAS threads left spinning beside the engine (`blas`)\n"
             "            frame = self._prepare(",
             "        if True:\n"
             "            frame = self._prepare(",
             ("tests/test_runtime.py::test_frame_preparation_holds_blas_to_one_thread",)),
    Mutation("OpenVINO's solver steps take the rotation Jacobian's third row with the wrong sign", "models/point_solver.py",
             "zt * au - x * az, x * av - y * au, nr]", "zt * au - x * az, y * au - x * av, nr]",
             ("tests/test_point_solver.py::test_confidence_one_is_the_numpy_tracker", "tests/test_sampling.py")),
    Mutation("a pipelined run opens the flow+pose stage on every thread, beside the reader's work", "d3lvo_deploy/backends.py",
             "        out[n] = sc.for_stage(n)\n",
             "        out[n] = sc.for_stage(\"encoder\")\n",
             ("tests/test_backends.py::test_a_pipelined_run_gives_the_flowpose_stage_one_thread_fewer",)),
    Mutation("a run that keeps each frame's tensors for pictures is pipelined three deep", "d3lvo_deploy/pipeline.py",
             "    return 2 if pictures else engine_depth(backend, splits)",
             "    return engine_depth(backend, splits)",
             ("tests/test_backends.py::test_a_pipelined_run_gives_the_flowpose_stage_one_thread_fewer",)),
    Mutation("a three-deep pipeline leaves the encoding to the main thread after all", "d3lvo_deploy/pipeline.py",
             "            encoded = odo.encode_timed(prepared) if deep and prepared is not None else None",
             "            encoded = None",
             ("tests/test_runtime.py::test_pipelined_run_writes_the_sequential_poses",)),
    Mutation("a frame's CPU half stays on one thread when two are asked for", "d3lvo_deploy/odometry.py",
             "        if threads < 2:\n            return functools.cache(job)",
             "        if True:\n            return functools.cache(job)",
             ("tests/test_point_solver.py::test_prepare_on_two_threads_gives_the_same_frame",)),
    Mutation("a pipelined run prepares frames on two threads beside the network", "d3lvo_deploy/backends.py",
             "threads=1 if depth == 3 else self.threads, prepare_threads=1,",
             "threads=1 if depth == 3 else self.threads,",
             ("tests/test_backends.py::test_a_pipelined_run_gives_the_flowpose_stage_one_thread_fewer",)),
    Mutation("a pipeline's reader prepares on the Odometry's own thread count", "d3lvo_deploy/pipeline.py",
             "odo.prepare(image, points, threads=1,", "odo.prepare(image, points,",
             ("tests/test_runtime.py::test_pipelined_run_writes_the_sequential_poses",)),
    Mutation("the export reuses a solver block across the two graphs' sampling layouts", "export/solver_loop.py",
             "               dynamic_batch, gathering())", "               dynamic_batch)",
             ("tests/test_point_solver.py::test_each_engines_graph_loops_over_its_own_steps",)),
    Mutation("bench refuses --precision for the default network at --height/--width", "cli/bench_cmd.py",
             'if precision != "fp32" and ckpt is None and not default_network:',
             'if precision != "fp32" and ckpt is None:',
             ("tests/test_bench.py::test_cli_bench_size_needs_both_and_no_fixed_folder",)),
    Mutation("the runtime imports onnxruntime with its module, before an export's traces", "d3lvo_deploy/backends.py",
             "from .errors import D3LVOInputError\n",
             "import onnxruntime  # noqa: F401\nfrom .errors import D3LVOInputError\n",
             ("tests/test_export.py::test_export_and_bench_load_no_engine_before_exporting",)),
    Mutation("completion and encoder keep every thread beside the classical solve", "d3lvo_deploy/backends.py",
             "            out[n] = replace(out[n], threads=max(1, sc.threads_taken - 1))\n",
             "            out[n] = out[n]\n",
             ("tests/test_backends.py::test_two_cores_solve_the_classical_mode_beside_completion_and_encoder",)),
    Mutation("the classical solve waits until completion and encoder are done", "d3lvo_deploy/odometry.py",
             "        beside = self._start_classical(frame.solver, frame.stamp)\n",
             "        beside = None\n",
             ("tests/test_point_solver.py::test_runtime_solves_the_classical_mode_beside_and_writes_the_batched_poses",)),
    Mutation("the flow+pose graph is given the pair's start as its classical pose", "d3lvo_deploy/odometry.py",
             "            inputs[CLASSICAL_INPUT] = self.model.solve_classical(inputs)\n",
             "            inputs[CLASSICAL_INPUT] = inputs[\"init_pose\"]\n",
             ("tests/test_point_solver.py::test_runtime_solves_the_classical_mode_beside_and_writes_the_batched_poses",)),
    Mutation("the scan's pass keeps the weighted pose where it fits the scan worse", "models/pose_points.py",
             "keep = keep | ((fits[:, 0] < self.cfg.pt_select_scan_pass * fits[:, 1]) & evidence)",
             "keep = keep | ((fits[:, 1] < self.cfg.pt_select_scan_pass * fits[:, 0]) & evidence)",
             ("tests/test_point_solver.py::test_frame_ts_scan_judges_between_the_weighted_and_the_classical_pose",
              "tests/test_point_solver.py::test_scan_judge_graph_takes_frame_ts_scan_and_equals_torch")),
    Mutation("the scan's errors count every point, not the trusted ones", "models/pose_points.py",
             "trusted = (weight >= 0.5).to(points.dtype)\n        return lidar_depth_error(",
             "trusted = (weight >= 0.0).to(points.dtype)\n        return lidar_depth_error(",
             ("tests/test_point_solver.py::test_frame_ts_scan_judges_between_the_weighted_and_the_classical_pose",)),
    Mutation("the scan's veto judges where a pose puts no trusted point on a return", "models/pose_points.py",
             "keep = keep & ((fits[:, 0] <= self.cfg.pt_select_scan * fits[:, 1]) | ~evidence)",
             "keep = keep & (fits[:, 0] <= self.cfg.pt_select_scan * fits[:, 1])",
             ("tests/test_point_solver.py::test_frame_ts_scan_judges_between_the_weighted_and_the_classical_pose",)),
    Mutation("the scan's pass judges where a pose puts no trusted point on a return", "models/pose_points.py",
             "keep = keep | ((fits[:, 0] < self.cfg.pt_select_scan_pass * fits[:, 1]) & evidence)",
             "keep = keep | (fits[:, 0] < self.cfg.pt_select_scan_pass * fits[:, 1])",
             ("tests/test_point_solver.py::test_frame_ts_scan_judges_between_the_weighted_and_the_classical_pose",)),
    Mutation("--resume continues poses of another start frame", "d3lvo_deploy/results.py",
             '"max_dt", "method", "start",\n', '"max_dt", "method",\n',
             ("tests/test_formats.py::test_resume_continues_only_the_run_its_config_records",)),
    Mutation("eval pairs TUM poses by their order, not their times", "d3lvo_deploy/evaluation.py",
             "    if est.timestamps is None or gt.timestamps is None or len(gt) < 2:\n",
             "    if True:\n",
             ("tests/test_metrics.py::test_timed_poses_pair_by_time_and_numbered_ones_by_number",)),
    Mutation("a calibration for images of another size runs without a word", "d3lvo_deploy/calib.py",
             "    if not (0 <= cx < width and 0 <= cy < height):", "    if False:",
             ("tests/test_calib.py::test_a_calibration_for_another_image_or_rig_is_caught",)),
    Mutation("a KITTI line whose 3x3 block is no rotation is read as a pose", "d3lvo_deploy/poses.py",
             "        bad = (off > ROTATION_TOLERANCE) | (det <= 0)", "        bad = np.zeros(len(R), bool)",
             ("tests/test_poses_io.py::test_bad_files_name_the_file",)),
    Mutation("the motion guard holds the previous step, not the previous speed, over a longer gap",
             "d3lvo_deploy/motion_guard.py",
             "    return scaled_motion(previous, dt / previous_dt), True", "    return previous, True",
             ("tests/test_motion_guard.py::test_the_guard_reads_speeds_so_a_dropped_frame_is_no_jump",)),
    Mutation("a guarded network pair's successor starts from the graph's own start", "d3lvo_deploy/odometry.py",
             "            if not held and start is not None and np.all(np.isfinite(start)):",
             "            if start is not None and np.all(np.isfinite(start)):",
             ("tests/test_motion_guard.py::test_network_run_keeps_the_previous_motion_and_starts_the_next_pair_from_it",)),
    Mutation("--resume continues a run made with another --max-accel", "d3lvo_deploy/results.py",
             '               "max_accel")', "               )",
             ("tests/test_motion_guard.py::test_resume_continues_only_a_run_with_the_same_guard",)),
    Mutation("a run stepping one frame at a time leaves out the frame's time", "d3lvo_deploy/pipeline.py",
             "pose = odo.step(image, points, float(seq.times[i]))", "pose = odo.step(image, points)",
             ("tests/test_motion_guard.py::test_run_reads_the_recordings_times",
              "tests/test_motion_guard.py::test_network_run_reads_the_recordings_times")),
    Mutation("a pipelined run's reader prepares frames without their times", "d3lvo_deploy/pipeline.py",
             "threads=1, stamp=float(seq.times[i]))", "threads=1)",
             ("tests/test_motion_guard.py::test_network_run_reads_the_recordings_times",)),
    Mutation("a resumed run primes without the time of the pose before", "d3lvo_deploy/pipeline.py",
             "previous_stamp=float(seq.times[k - 1]) if len(done) >= 2 else None)", "previous_stamp=None)",
             ("tests/test_motion_guard.py::test_run_reads_the_recordings_times",
              "tests/test_motion_guard.py::test_network_run_reads_the_recordings_times")),
    Mutation("the classical tracker starts a pair across a dropped frame from the last pair's motion",
             "d3lvo_deploy/direct.py",
             "track(self._prev, cur, scaled_motion(self.motion2, dt / self.motion_dt), self.cfg)",
             "track(self._prev, cur, self.motion2, self.cfg)",
             ("tests/test_motion_guard.py::test_run_reads_the_recordings_times",)),
    Mutation("the network starts a pair across a dropped frame from the last pair's motion", "d3lvo_deploy/odometry.py",
             "        gap = self.guard.interval(self._prev_stamp, stamp) / self.kept_dt\n", "        gap = 1.0\n",
             ("tests/test_motion_guard.py::test_network_run_reads_the_recordings_times",)),
    Mutation("the classical tracker's scan gate drops the points that stayed where the start puts them",
             "d3lvo_deploy/direct.py",
             "nan=0.0) > limit", "nan=0.0) <= limit",
             ("tests/test_direct.py::test_scan_gate_drops_what_moved",)),
    Mutation("the classical tracker's scan gate drops the points without a return", "d3lvo_deploy/direct.py",
             "depth_errors(prev.points, start, depth, prev.levels[0].K), nan=0.0)",
             "depth_errors(prev.points, start, depth, prev.levels[0].K), nan=1.0)",
             ("tests/test_direct.py::test_scan_gate_drops_what_moved",)),
    Mutation("the graph's scan gate judges the points at rest instead of at the start", "models/point_solver.py",
             "    errors, seen = depth_errors(init, points, depth2, K)",
             "    errors, seen = depth_errors(init * 0 + torch.eye(4, dtype=init.dtype), points, depth2, K)",
             ("tests/test_point_solver.py::test_scan_gate_is_the_numpy_trackers",)),
    Mutation("the model's scan gate is not the classical mode's", "d3lvo_deploy/direct.py",
             'scan_gate=float(model_config.get("pt_scan_gate", 0.0))', 'scan_gate=0.0',
             ("tests/test_direct.py::test_scan_gate_comes_from_the_model",)),
    Mutation("the classical tracker counts the median's stride in the list the scan gate thinned",
             "d3lvo_deploy/direct.py",
             "np.flatnonzero(ok) if index is None else index[ok], cfg.median_stride)",
             "np.flatnonzero(ok), cfg.median_stride)",
             ("tests/test_point_solver.py::test_scan_gate_is_the_numpy_trackers",)),
    Mutation("OpenVINO bf16 allowed where oneDNN is held below its bf16 kernels", "d3lvo_deploy/cpu.py",
             "and (max_isa or \"\").strip().upper() not in _BELOW_BF16", "",
             ("tests/test_backends.py::test_bf16_kernels_need_the_extension_and_onednn_not_held_below_them",
              "tests/test_backends.py::test_bf16_on_a_cpu_without_it_is_one_clear_error")),
    Mutation("OpenVINO's load error reports its first line (a source file)", "d3lvo_deploy/backends.py",
             "return ((said or lines or [type(e).__name__])[-1])[:200]",
             "return ((lines or [type(e).__name__])[0])[:200]",
             ("tests/test_backends.py::test_openvino_errors_name_the_reason_not_the_source_file",)),
    Mutation("OpenVINO's load error quotes the first line of its text", "d3lvo_deploy/backends.py",
             'f"OpenVINO cannot load it ({openvino_reason(e)})"',
             'f"OpenVINO cannot load it ({str(e).splitlines()[0][:200]})"',
             ("tests/test_backends.py::test_an_openvino_load_error_names_the_file_and_the_reason",)),
]


def scratch_copy(dest: Path) -> None:
    archive = subprocess.run(["git", "archive", "HEAD"], cwd=ROOT, check=True, capture_output=True).stdout
    subprocess.run(["tar", "-x", "-C", str(dest)], input=archive, check=True)


def apply(m: Mutation, tree: Path) -> None:
    if m.script:
        subprocess.run([sys.executable, "-c", m.script], cwd=tree, check=True, capture_output=True)
        return
    path = tree / m.file
    text = path.read_text()
    if text.count(m.old) != 1:
        raise SystemExit(f"mutation {m.name!r}: the text to replace is not found exactly once in {m.file}")
    path.write_text(text.replace(m.old, m.new))


def run_tests(tree: Path, tests: tuple[str, ...]) -> tuple[bool, list[str]]:
    env_check = subprocess.run([sys.executable, "-c", "import d3lvo_deploy, models; print(d3lvo_deploy.__file__)"],
                               cwd=tree, capture_output=True, text=True, check=True).stdout
    if not env_check.startswith(str(tree)):
        raise SystemExit(f"the scratch copy imports the checkout's package ({env_check.strip()}), not its own")
    r = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", *tests], cwd=tree,
                       capture_output=True, text=True)
    if r.returncode in (3, 4, 5):  # internal error, usage error (a test id not found), nothing collected
        raise SystemExit(f"pytest could not run {' '.join(tests)} (exit {r.returncode}):\n{r.stdout[-2000:]}")
    failed = [ln.split(" ", 1)[1].split(" - ")[0] for ln in r.stdout.splitlines() if ln.startswith(("FAILED", "ERROR"))]
    return r.returncode in (1, 2), failed  # 2: a collection error, which the suite would show too


def main(argv: list[str]) -> int:
    chosen = [int(a) for a in argv] or list(range(1, len(MUTATIONS) + 1))
    missed = 0
    for k in chosen:
        m = MUTATIONS[k - 1]
        with tempfile.TemporaryDirectory(prefix=f"d3lvo-mutation-{k}-") as d:
            tree = Path(d) / ROOT.name
            tree.mkdir()
            scratch_copy(tree)
            if (ROOT.parent / "shared").is_dir():  # the tests on real KITTI files find ../shared/data
                (Path(d) / "shared").symlink_to(ROOT.parent / "shared")
            apply(m, tree)
            caught, failed = run_tests(tree, m.tests)
        missed += not caught
        print(f"{k}. {m.name}: {'CAUGHT by ' + ', '.join(failed) if caught else 'MISSED'}", flush=True)
    return 1 if missed else 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
