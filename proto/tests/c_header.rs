//! include/graspd.h, the contract for C and C++ clients, says what the Rust
//! definitions say: every field's offset and size, every type's size,
//! alignment and iceoryx2 type name, every constant. The header is compiled
//! as C11 and as C++17 with warnings as errors, and a probe built from it
//! prints those facts (tests/c/layout_probe.c).

use std::collections::BTreeSet;
use std::mem::{align_of, offset_of, size_of};
use std::path::{Path, PathBuf};
use std::process::Command;

use graspd_proto::*;
use iceoryx2::prelude::ZeroCopySend;

fn size_of_field<T, F>(_: fn(&T) -> &F) -> usize {
    size_of::<F>()
}

/// A type's line and one line per field, as the probe prints them; checks on
/// the way that the fields listed tile the type (so none is left out).
macro_rules! wire_type {
    ($facts:ident, $t:ident { $($f:ident),* $(,)? }) => {{
        // SAFETY: type_name only returns the name given to the derive.
        let type_name = unsafe { <$t as ZeroCopySend>::type_name() };
        $facts.push(format!("type {} {} {} {}", stringify!($t), size_of::<$t>(), align_of::<$t>(), type_name));
        let mut end = 0;
        $(
            let offset = offset_of!($t, $f);
            let size = size_of_field(|v: &$t| &v.$f);
            assert_eq!(offset, end, "{}::{} does not follow the field before it: a field is missing from this list", stringify!($t), stringify!($f));
            end = offset + size;
            $facts.push(format!("field {} {} {} {}", stringify!($t), stringify!($f), offset, size));
        )*
        assert_eq!(end, size_of::<$t>(), "the fields listed of {} do not fill it", stringify!($t));
    }};
}

/// What the Rust definitions say, in the probe's words.
fn rust_facts() -> BTreeSet<String> {
    let mut facts = Vec::new();
    wire_type!(
        facts,
        RequestHeader {
            request_id,
            deadline_unix_ns,
            notify_token,
            seed,
            protocol_version,
            flags,
            category,
            cloud_frame,
            up_in_cloud,
            table_mode,
            table_z_m,
            pregrasp_backoff_m,
            pregrasp_joint_fraction,
            viewpoint_in_cloud_m,
            second_viewpoint_in_cloud_m,
            reserved,
        }
    );
    // Point is a tuple struct; the header names its one field `xyz`.
    // SAFETY: as above.
    let point_name = unsafe { <Point as ZeroCopySend>::type_name() };
    facts.push(format!("type Point {} {} {point_name}", size_of::<Point>(), align_of::<Point>()));
    facts.push(format!("field Point xyz {} {}", offset_of!(Point, 0), size_of::<[f32; 3]>()));
    assert_eq!(size_of::<Point>(), size_of::<[f32; 3]>());
    wire_type!(facts, NoPayload { reserved });
    wire_type!(facts, ResponseHeader { request_id, server_ns, compute_ns, status, protocol_version, message });
    wire_type!(
        facts,
        HealthResponse {
            uptime_ns,
            startup_ns,
            pid,
            protocol_version,
            serving,
            waiting,
            categories,
            max_points,
            max_in_flight_per_client,
            workers,
            grasp_available,
            hand_actuated_joints,
            server_version,
            hand_name,
        }
    );
    wire_type!(
        facts,
        CategoryInfo { name, latent_dim, keypoint_count, keypoint_names, canonical_frame, grasp_available, reserved }
    );
    wire_type!(facts, CategoriesResponse { count, reserved, categories });
    wire_type!(facts, Keypoint { name, position_cloud_m });
    wire_type!(
        facts,
        Registration {
            latent,
            rotation_cloud_from_canonical_xyzw,
            translation_cloud_from_canonical_m,
            scale,
            sigma2_m2,
            inlier_fraction,
            residual_m,
            inlier_threshold_m,
            viewpoint_cloud_m,
            coverage,
            view_width_m,
            latent_mahalanobis,
            contradicted_fraction,
            latent_dim,
            keypoint_count,
            confident,
            points,
            ambiguous_pose,
            stray_points,
            viewpoint_source,
            yaw_half_width_rad,
            table_points,
            reserved,
            keypoints,
        }
    );
    wire_type!(facts, RegisterResponse { registration });
    wire_type!(
        facts,
        HandConfiguration { rotation_cloud_from_wrist_xyzw, translation_cloud_from_wrist_m, actuated, joints }
    );
    wire_type!(
        facts,
        GraspResponse {
            registration,
            grasp,
            pregrasp,
            actuated_names,
            joint_names,
            task_space_distance_m,
            residual_mean_m,
            residual_max_m,
            penetration_m,
            pregrasp_min_clearance_m,
            table_z_m,
            actuated_count,
            joint_count,
            table_used,
            pregrasp_collision_free,
            warnings,
            reserved,
        }
    );
    wire_type!(
        facts,
        MethodStats {
            name,
            requests,
            by_status,
            slow,
            latency_p50_us,
            latency_p90_us,
            latency_p99_us,
            latency_max_us,
            compute_p50_us,
            compute_p99_us,
            window,
            in_flight,
        }
    );
    wire_type!(facts, StatsResponse { uptime_ns, rss_bytes, clients_connected, queued, method_count, methods });

    let numbers: Vec<(&str, u64)> = vec![
        ("GRASPD_PROTOCOL_VERSION", PROTOCOL_VERSION as u64),
        ("GRASPD_NAME_LEN", size_of::<Name>() as u64),
        ("GRASPD_MAX_KEYPOINTS", MAX_KEYPOINTS as u64),
        ("GRASPD_MAX_LATENT", MAX_LATENT as u64),
        ("GRASPD_MAX_CATEGORIES", MAX_CATEGORIES as u64),
        ("GRASPD_MAX_JOINTS", MAX_JOINTS as u64),
        ("GRASPD_MAX_METHODS", MAX_METHODS as u64),
        ("GRASPD_MESSAGE_LEN", MESSAGE_LEN as u64),
        ("GRASPD_FRAME_TEXT_LEN", FRAME_TEXT_LEN as u64),
        ("GRASPD_METHOD_HEALTH", Method::Health as u64),
        ("GRASPD_METHOD_LIST_CATEGORIES", Method::ListCategories as u64),
        ("GRASPD_METHOD_REGISTER", Method::Register as u64),
        ("GRASPD_METHOD_GRASP", Method::Grasp as u64),
        ("GRASPD_METHOD_STATS", Method::Stats as u64),
        ("GRASPD_STATUS_OK", StatusCode::Ok as u64),
        ("GRASPD_STATUS_INVALID_ARGUMENT", StatusCode::InvalidArgument as u64),
        ("GRASPD_STATUS_DEADLINE_EXCEEDED", StatusCode::DeadlineExceeded as u64),
        ("GRASPD_STATUS_NOT_FOUND", StatusCode::NotFound as u64),
        ("GRASPD_STATUS_RESOURCE_EXHAUSTED", StatusCode::ResourceExhausted as u64),
        ("GRASPD_STATUS_FAILED_PRECONDITION", StatusCode::FailedPrecondition as u64),
        ("GRASPD_STATUS_INTERNAL", StatusCode::Internal as u64),
        ("GRASPD_STATUS_UNAVAILABLE", StatusCode::Unavailable as u64),
        ("GRASPD_FLAG_VIEWPOINT", flags::VIEWPOINT as u64),
        ("GRASPD_FLAG_SECOND_VIEWPOINT", flags::SECOND_VIEWPOINT as u64),
        ("GRASPD_FLAGS_ALL", flags::ALL as u64),
        ("GRASPD_TABLE_MODE_AUTO", table_mode::AUTO as u64),
        ("GRASPD_TABLE_MODE_NONE", table_mode::NONE as u64),
        ("GRASPD_TABLE_MODE_GIVEN", table_mode::GIVEN as u64),
        ("GRASPD_GRASP_WARNING_REGISTRATION_NOT_CONFIDENT", grasp_warning::REGISTRATION_NOT_CONFIDENT as u64),
        ("GRASPD_GRASP_WARNING_PREGRASP_IN_COLLISION", grasp_warning::PREGRASP_IN_COLLISION as u64),
        ("GRASPD_GRASP_WARNING_NO_TABLE_FRAME_NOT_Z_UP", grasp_warning::NO_TABLE_FRAME_NOT_Z_UP as u64),
        ("GRASPD_VIEWPOINT_SOURCE_NONE", viewpoint_source::NONE as u64),
        ("GRASPD_VIEWPOINT_SOURCE_GIVEN", viewpoint_source::GIVEN as u64),
        ("GRASPD_VIEWPOINT_SOURCE_ESTIMATED", viewpoint_source::ESTIMATED as u64),
        ("GRASPD_SERVING", serving::SERVING as u64),
        ("GRASPD_DRAINING", serving::DRAINING as u64),
        ("GRASPD_WAITING_EVENT", waiting::EVENT as u64),
        ("GRASPD_WAITING_POLL", waiting::POLL as u64),
    ];
    facts.extend(numbers.into_iter().map(|(name, value)| format!("const {name} {value}")));
    let texts = [
        ("GRASPD_VERSION_SEGMENT", VERSION_SEGMENT),
        ("GRASPD_DEFAULT_PREFIX", DEFAULT_PREFIX),
        ("GRASPD_ATTRIBUTE_PROTOCOL_VERSION", attribute::PROTOCOL_VERSION),
        ("GRASPD_METHOD_HEALTH_NAME", Method::Health.name()),
        ("GRASPD_METHOD_LIST_CATEGORIES_NAME", Method::ListCategories.name()),
        ("GRASPD_METHOD_REGISTER_NAME", Method::Register.name()),
        ("GRASPD_METHOD_GRASP_NAME", Method::Grasp.name()),
        ("GRASPD_METHOD_STATS_NAME", Method::Stats.name()),
    ];
    facts.extend(texts.into_iter().map(|(name, value)| format!("text {name} {value}")));
    // Every method and status code of the Rust contract has its line.
    assert_eq!(Method::ALL.len(), 5);
    assert_eq!(StatusCode::ALL.len(), 8);
    let count = facts.len();
    let set: BTreeSet<String> = facts.into_iter().collect();
    assert_eq!(set.len(), count, "a fact listed twice");
    set
}

/// Compiles the probe with `compiler` and `args` and returns what it prints;
/// None when the compiler is not installed.
fn probe(compiler: &str, args: &[&str], out: &Path) -> Option<BTreeSet<String>> {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let compiled = Command::new(compiler)
        .args(args)
        .arg("-Wall")
        .arg("-Wextra")
        .arg("-Wpedantic")
        .arg("-Werror")
        .arg("-I")
        .arg(root.join("include"))
        .arg(root.join("tests/c/layout_probe.c"))
        .arg("-o")
        .arg(out)
        .output();
    let compiled = match compiled {
        Ok(o) => o,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return None,
        Err(e) => panic!("running {compiler}: {e}"),
    };
    assert!(
        compiled.status.success(),
        "{compiler} {args:?} failed on include/graspd.h:\n{}",
        String::from_utf8_lossy(&compiled.stderr)
    );
    let ran = Command::new(out).output().expect("running the probe");
    assert!(ran.status.success());
    Some(String::from_utf8(ran.stdout).expect("the probe prints UTF-8").lines().map(str::to_owned).collect())
}

fn assert_same(language: &str, header: &BTreeSet<String>, rust: &BTreeSet<String>) {
    let missing: Vec<_> = rust.difference(header).collect();
    let extra: Vec<_> = header.difference(rust).collect();
    assert!(
        missing.is_empty() && extra.is_empty(),
        "include/graspd.h as {language} differs from the Rust contract.\nRust says, the header does not: {missing:#?}\nThe header says, Rust does not: {extra:#?}"
    );
}

fn out_path(name: &str) -> PathBuf {
    Path::new(env!("CARGO_TARGET_TMPDIR")).join(name)
}

#[test]
fn the_c_header_says_what_the_rust_contract_says() {
    let rust = rust_facts();
    let cc = std::env::var("CC").unwrap_or_else(|_| "cc".into());
    let Some(c) = probe(&cc, &["-x", "c", "-std=c11"], &out_path("graspd_h_probe_c")) else {
        eprintln!("skipped: no C compiler `{cc}` (set CC)");
        return;
    };
    assert_same("C11", &c, &rust);
}

#[test]
fn the_header_as_cpp_names_each_type_as_iceoryx2_does() {
    let rust = rust_facts();
    let cxx = std::env::var("CXX").unwrap_or_else(|_| "c++".into());
    let Some(cpp) = probe(&cxx, &["-x", "c++", "-std=c++17"], &out_path("graspd_h_probe_cpp")) else {
        eprintln!("skipped: no C++ compiler `{cxx}` (set CXX)");
        return;
    };
    assert_same("C++17", &cpp, &rust);
}
