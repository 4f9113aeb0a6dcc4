"""Shared test set-up: paths, the shared-data marker, small fixtures and helpers, the fast tier's slow marks.

The tests mirror the package: ``tests/<subpackage>/test_<module>.py``
(``tests/project/`` for checks of the whole repository); every test file's
name is unique, so the marks below are keyed by file name.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

os.environ.setdefault("O3DRBF_NO_PROGRESS", "1")  # before o3drbf is imported
from o3drbf.constraints.core import EXTERIOR, SPHERE, SURFACE, Constraints, bounding_sphere  # noqa: E402
from o3drbf.rbf.kernels import make_kernel  # noqa: E402
from o3drbf.synthetic.shapes import Sphere  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"


def shared_data_or_skip() -> Path:
    """The ../shared/data folder, or skip the test with the reason."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"needs the shared data folder {SHARED_DATA} (not present: a clone without ../shared)")
    return SHARED_DATA


@pytest.fixture
def rng():
    return np.random.default_rng(12345)


# -- shared by constraints/test_robust.py and solvers/test_refit.py ------------------------------------

#: The robust-fit sphere (constraints/test_robust.py, solvers/test_refit.py): radius and samples (box units), and the kernel.
ROBUST_R = 0.8
ROBUST_N = 500
ROBUST_KERNEL = make_kernel("multiorder", delta=10.0, tau=0.01)


def sphere_constraints(outlier_fraction, noise=0.0, seed=0):
    """Samples of a sphere of radius ROBUST_R (box units) plus gross outliers 15-40% of ROBUST_R off it, in or out (last rows)."""
    pts, _ = Sphere(ROBUST_R).sample(ROBUST_N, noise=noise, seed=seed)
    rng = np.random.default_rng(seed + 1)
    k = int(round(outlier_fraction * ROBUST_N))
    d = rng.normal(size=(k, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    out = d * (ROBUST_R * (1 + rng.choice([-1.0, 1.0], k) * rng.uniform(0.15, 0.4, k)))[:, None]
    c = Constraints.concat(
        Constraints.of_kind(np.vstack([pts, out]), SURFACE, 1e-3),
        Constraints.of_kind(pts[::10] * (1 + 0.05 / ROBUST_R), EXTERIOR, 2.0),
        Constraints.of_kind(bounding_sphere(pts, 64), SPHERE, 2.0),
    )
    return c, pts, k


def radial_error(surface, directions):
    """Mean |r - ROBUST_R| of the fitted zero set along rays from the centre (bisection; truth: the sphere)."""
    d = directions / np.linalg.norm(directions, axis=1, keepdims=True)
    lo, hi = np.full(len(d), 0.3 * ROBUST_R), np.full(len(d), 1.7 * ROBUST_R)
    assert (surface.evaluate_box(d * lo[:, None]) > 0).all() and (surface.evaluate_box(d * hi[:, None]) < 0).all()
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        inside = surface.evaluate_box(d * mid[:, None]) > 0
        lo, hi = np.where(inside, mid, lo), np.where(inside, hi, mid)
    return float(np.abs(0.5 * (lo + hi) - ROBUST_R).mean())


#: The fast tier (``make test-fast``: ``pytest -m "not slow"``) leaves out the
#: tests marked ``slow``: whole modules that run end to end (real data, Dask
#: clusters, subprocesses, builds, notebooks), and the tests that took more
#: than about 1.5 s beside other work (``pytest --durations=0``; about 0.5 s
#: on idle cores), and those that use an expensive module fixture
#: (:data:`SLOW_FIXTURES`).  A new test is marked with ``@pytest.mark.slow``
#: or listed here; every parametrization of a listed test is slow.
SLOW_MODULES = {
    "test_logs.py", "test_notebook.py", "test_packaging.py", "test_readme.py", "test_real_bunny.py", "test_robust_default.py",
    "test_tiles.py", "test_tiles_outofcore.py", "test_tiles_parity.py", "test_tiles_lidar.py",
}
SLOW_TESTS = {
    "test_sparse.py": {"test_sparse_cloud_gives_one_closed_piece"},
    "test_fast_memory.py": {"test_cli_refuses_a_large_fit_right_after_reading", "test_looser_companions_never_take_a_finer_grid",
                            "test_fast_refusal_is_up_front_and_names_a_count_that_fits",
                            "test_plan_is_within_a_factor_of_the_measured_peak"},
    "test_parameters.py": {
        "test_auto_beats_the_paper_values_on_a_noisy_torus", "test_cli_defaults_to_auto_and_no_auto_gives_the_paper_values",
        "test_explicit_values_win_and_stats_record_the_source"
    },
    "test_camera_pipeline.py": {"test_cli_plain_ply_with_camera_file", "test_cli_scan_json_and_api_with_cameras"},
    "test_cli.py": {
        "test_coloured_input_gives_a_coloured_mesh", "test_compare_subcommand", "test_points_without_normals",
        "test_surface_radius_and_all_points", "test_usage_errors_and_entry_point"
    },
    "test_color.py": {"test_known_colours_are_recovered_on_a_reconstructed_torus"},
    "test_compare.py": {
        "test_poisson_both_ways_on_scans_with_outliers", "test_both_poissons_get_the_clouds_normals",
        "test_main_compare_end_to_end", "test_picture_distance_colours_and_hidden_pieces", "test_picture_grid",
        "test_rows_and_measures", "test_shifted_truth_fails_the_bound"
    },
    "test_confidence.py": {
        "test_trim_half_sphere_sample_is_one_disc",
        "test_a_kernel_without_a_covariance_is_refused_and_confidence_falls_back_to_distance",
        "test_command_line_confidence_and_trim", "test_one_camera_seeing_one_side_of_a_sphere",
        "test_trim_removes_the_unseen_part_and_leaves_an_open_surface"
    },
    "test_denoise.py": {"test_reconstruct_denoises_noisy_scans_and_leaves_clean_ones"},
    "test_extract.py": {"test_grid_evaluator_mesh_matches_exact_evaluation_within_a_fraction_of_a_voxel"},
    "test_fast.py": {
        "test_evaluator_values_and_gradients", "test_fast_solve_matches_dense", "test_grid_product_matches_dense",
        "test_grid_solve_matches_dense", "test_iteration_count_nearly_flat", "test_nested_coarse_level_restores_the_count",
        "test_product_matches_dense", "test_solve_entry_point_and_gaussian", "test_unreachable_tolerance_warns_with_residual",
        "test_mesh_tolerance_moves_the_surface_by_about_the_asked_fraction_of_a_cell"
    },
    "test_fast_auto.py": {
        "test_fast_solve_matches_dense_at_auto_extremes", "test_grid_chosen_under_budget_with_the_exterior_sphere"
    },
    "test_faults.py": {
        "test_cli_file_size_limit_in_subprocess", "test_disk_limit_and_sigterm_leave_no_partial_file",
        "test_soak_repeated_reconstructions_bounded_memory"
    },
    "test_intersections.py": {
        "test_marching_cubes_of_noisy_functions", "test_overlapping_spheres_merged", "test_primitives_alone_shifted_and_noisy",
        "test_timing_300k_triangles"
    },
    "test_kernels.py": {"test_kernel_matrix_is_positive_definite", "test_tabulated_kernel_matches_the_exact_one"},
    "test_lidar.py": {
        "test_cli_tiles_on_e57_uses_the_scanners", "test_e57_reconstructs_the_torus_with_its_scanners",
        "test_las_and_laz_read_back_and_reconstruct_a_sphere"
    },
    "test_options.py": {
        "test_a_kernel_defined_in_a_test_works_end_to_end", "test_automatic_sizes_follow_the_data",
        "test_stages_alone_give_what_reconstruct_gives"
    },
    "test_photos.py": {
        "test_bundler_file_kept_apart_from_its_images", "test_cli_writes_coloured_mesh_and_picture",
        "test_colmap_model_with_an_images_folder", "test_synthetic_photographs_give_the_coloured_sphere",
        "test_temple_silhouettes_match"
    },
    "test_reconstruct.py": {
        "test_deterministic_and_accepts_open3d_point_clouds", "test_fast_solver_gives_the_dense_surface",
        "test_lambda_zero_interpolates_the_constraints", "test_more_smoothing_is_smoother_and_fits_less",
        "test_oversmoothing_that_erases_the_surface_says_what_to_change", "test_sphere_radius_recovered_within_one_percent",
        "test_torus_is_watertight_manifold_genus_one", "test_without_normals_they_are_estimated_and_logged"
    },
    "test_refit.py": {
        "test_fast_refits_start_from_the_previous_solution_and_agree_with_a_dense_solve",
        "test_fast_refits_reuse_the_first_refits_preconditioner_set_to_the_new_smoothing",
        "test_fast_solves_run_in_spatial_order_and_answer_in_the_callers",
        "test_lower_kernel_matrix_is_the_full_matrix_lower_triangle", "test_many_changes_solve_afresh_and_agree",
        "test_refits_reuse_back_substitutions_and_stay_exact", "test_robust_refits_by_update_equal_refits_by_fresh_fits",
        "test_woodbury_update_equals_a_fresh_solve"
    },
    "test_registration.py": {
        "test_reconstruct_leaves_registered_scans_alone", "test_reconstruct_registers_misregistered_scans_by_default",
        "test_recovers_a_known_misregistration", "test_register_scans_turns_normals_with_their_scan",
        "test_registered_scans_are_left_exactly_as_they_were", "test_thin_walls_are_not_pulled_together"
    },
    "test_robust.py": {
        "test_local_residuals_fall_back_when_the_check_sees_a_move", "test_noisy_sphere_with_outliers",
        "test_residuals_measured_again_only_near_the_changes", "test_robust_fit_recovers_the_clean_fit"
    },
    "test_sampling.py": {"test_poisson_disc_count_separation_coverage_determinism"},
    "test_solve.py": {"test_dense_matches_independent_solve"},
    "test_solver_properties.py": {
        "test_invariances", "test_lambda_zero_interpolates", "test_per_point_smoothing_discounts_an_outlier",
        "test_per_point_smoothing_obeys_the_equations"
    },
    "test_sources.py": {"test_voxel_shell_to_points_and_reconstruction"},
    "test_startup.py": {
        "test_importing_o3drbf_and_open3d_leaves_dash_and_plotly_unloaded_until_used", "test_open3d_imported_first_is_left_alone",
        "test_report_json_has_the_summary_and_every_stage", "test_set_up_warm_up_leaves_nothing_to_compile_on_a_first_run"
    },
    "test_viewer.py": {
        "test_a_mesh_is_shown_as_it_is_coloured_by_a_field", "test_dense_points_leave_the_surface_visible",
        "test_distance_to_another_mesh_colours_both_panels_with_one_range", "test_help_and_import_need_no_display_or_pyvista",
        "test_interactive_app_under_xvfb_responds_to_sliders", "test_layers_toggle_what_is_drawn",
        "test_mesh_window_under_xvfb_keys_toggle_only_their_layer", "test_screenshot_cli_shows_points_constraints_and_surface",
        "test_slider_labels_do_not_overlap", "test_sliders_refit_or_reextract"
    },
}


#: Module fixtures whose set-up is a whole comparison or reconstruction.
SLOW_FIXTURES = {"test_compare.py": {"run"}}


def pytest_collection_modifyitems(config, items):
    """Mark the tests of :data:`SLOW_MODULES`, :data:`SLOW_TESTS` and :data:`SLOW_FIXTURES` ``slow``."""
    for item in items:
        module = item.path.name
        name = getattr(item, "originalname", item.name)
        fixtures = set(getattr(item, "fixturenames", ()))
        if module in SLOW_MODULES or name in SLOW_TESTS.get(module, ()) or fixtures & SLOW_FIXTURES.get(module, set()):
            item.add_marker(pytest.mark.slow)
