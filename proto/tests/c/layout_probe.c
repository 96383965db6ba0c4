/*
 * Prints what proto/include/graspd.h says of the wire, one fact per line, for
 * proto/tests/c_header.rs to compare with the Rust definitions. Compiled as C
 * (the type names from the GRASPD_TYPE_NAME_* strings) and as C++ (from each
 * type's IOX2_TYPE_NAME, what iceoryx2's C++ bindings read).
 */
#include "graspd.h"

#include <stdio.h>

#ifdef __cplusplus
#define ALIGN_OF(T) alignof(T)
#define TYPE(T, c_name) \
    printf("type %s %zu %zu %s\n", #T, sizeof(graspd_##T), ALIGN_OF(graspd_##T), graspd_##T::IOX2_TYPE_NAME)
#else
#define ALIGN_OF(T) _Alignof(T)
#define TYPE(T, c_name) printf("type %s %zu %zu %s\n", #T, sizeof(graspd_##T), ALIGN_OF(graspd_##T), c_name)
#endif

#define FIELD(T, f) \
    printf("field %s %s %zu %zu\n", #T, #f, offsetof(graspd_##T, f), sizeof(((graspd_##T*) 0)->f))
#define NUMBER(name) printf("const %s %lu\n", #name, (unsigned long) (name))
#define TEXT(name) printf("text %s %s\n", #name, name)

int main(void) {
    TYPE(RequestHeader, GRASPD_TYPE_NAME_REQUEST_HEADER);
    FIELD(RequestHeader, request_id);
    FIELD(RequestHeader, deadline_unix_ns);
    FIELD(RequestHeader, notify_token);
    FIELD(RequestHeader, seed);
    FIELD(RequestHeader, protocol_version);
    FIELD(RequestHeader, flags);
    FIELD(RequestHeader, category);
    FIELD(RequestHeader, cloud_frame);
    FIELD(RequestHeader, up_in_cloud);
    FIELD(RequestHeader, table_mode);
    FIELD(RequestHeader, table_z_m);
    FIELD(RequestHeader, pregrasp_backoff_m);
    FIELD(RequestHeader, pregrasp_joint_fraction);
    FIELD(RequestHeader, viewpoint_in_cloud_m);
    FIELD(RequestHeader, second_viewpoint_in_cloud_m);
    FIELD(RequestHeader, reserved);

    TYPE(Point, GRASPD_TYPE_NAME_POINT);
    FIELD(Point, xyz);

    TYPE(NoPayload, GRASPD_TYPE_NAME_NO_PAYLOAD);
    FIELD(NoPayload, reserved);

    TYPE(ResponseHeader, GRASPD_TYPE_NAME_RESPONSE_HEADER);
    FIELD(ResponseHeader, request_id);
    FIELD(ResponseHeader, server_ns);
    FIELD(ResponseHeader, compute_ns);
    FIELD(ResponseHeader, status);
    FIELD(ResponseHeader, protocol_version);
    FIELD(ResponseHeader, message);

    TYPE(HealthResponse, GRASPD_TYPE_NAME_HEALTH_RESPONSE);
    FIELD(HealthResponse, uptime_ns);
    FIELD(HealthResponse, startup_ns);
    FIELD(HealthResponse, pid);
    FIELD(HealthResponse, protocol_version);
    FIELD(HealthResponse, serving);
    FIELD(HealthResponse, waiting);
    FIELD(HealthResponse, categories);
    FIELD(HealthResponse, max_points);
    FIELD(HealthResponse, max_in_flight_per_client);
    FIELD(HealthResponse, workers);
    FIELD(HealthResponse, grasp_available);
    FIELD(HealthResponse, hand_actuated_joints);
    FIELD(HealthResponse, server_version);
    FIELD(HealthResponse, hand_name);

    TYPE(CategoryInfo, GRASPD_TYPE_NAME_CATEGORY_INFO);
    FIELD(CategoryInfo, name);
    FIELD(CategoryInfo, latent_dim);
    FIELD(CategoryInfo, keypoint_count);
    FIELD(CategoryInfo, keypoint_names);
    FIELD(CategoryInfo, canonical_frame);
    FIELD(CategoryInfo, grasp_available);
    FIELD(CategoryInfo, reserved);

    TYPE(CategoriesResponse, GRASPD_TYPE_NAME_CATEGORIES_RESPONSE);
    FIELD(CategoriesResponse, count);
    FIELD(CategoriesResponse, reserved);
    FIELD(CategoriesResponse, categories);

    TYPE(Keypoint, GRASPD_TYPE_NAME_KEYPOINT);
    FIELD(Keypoint, name);
    FIELD(Keypoint, position_cloud_m);

    TYPE(Registration, GRASPD_TYPE_NAME_REGISTRATION);
    FIELD(Registration, latent);
    FIELD(Registration, rotation_cloud_from_canonical_xyzw);
    FIELD(Registration, translation_cloud_from_canonical_m);
    FIELD(Registration, scale);
    FIELD(Registration, sigma2_m2);
    FIELD(Registration, inlier_fraction);
    FIELD(Registration, residual_m);
    FIELD(Registration, inlier_threshold_m);
    FIELD(Registration, viewpoint_cloud_m);
    FIELD(Registration, coverage);
    FIELD(Registration, view_width_m);
    FIELD(Registration, latent_mahalanobis);
    FIELD(Registration, contradicted_fraction);
    FIELD(Registration, latent_dim);
    FIELD(Registration, keypoint_count);
    FIELD(Registration, confident);
    FIELD(Registration, points);
    FIELD(Registration, ambiguous_pose);
    FIELD(Registration, stray_points);
    FIELD(Registration, viewpoint_source);
    FIELD(Registration, yaw_half_width_rad);
    FIELD(Registration, table_points);
    FIELD(Registration, reserved);
    FIELD(Registration, keypoints);

    TYPE(RegisterResponse, GRASPD_TYPE_NAME_REGISTER_RESPONSE);
    FIELD(RegisterResponse, registration);

    TYPE(HandConfiguration, GRASPD_TYPE_NAME_HAND_CONFIGURATION);
    FIELD(HandConfiguration, rotation_cloud_from_wrist_xyzw);
    FIELD(HandConfiguration, translation_cloud_from_wrist_m);
    FIELD(HandConfiguration, actuated);
    FIELD(HandConfiguration, joints);

    TYPE(GraspResponse, GRASPD_TYPE_NAME_GRASP_RESPONSE);
    FIELD(GraspResponse, registration);
    FIELD(GraspResponse, grasp);
    FIELD(GraspResponse, pregrasp);
    FIELD(GraspResponse, actuated_names);
    FIELD(GraspResponse, joint_names);
    FIELD(GraspResponse, task_space_distance_m);
    FIELD(GraspResponse, residual_mean_m);
    FIELD(GraspResponse, residual_max_m);
    FIELD(GraspResponse, penetration_m);
    FIELD(GraspResponse, pregrasp_min_clearance_m);
    FIELD(GraspResponse, table_z_m);
    FIELD(GraspResponse, actuated_count);
    FIELD(GraspResponse, joint_count);
    FIELD(GraspResponse, table_used);
    FIELD(GraspResponse, pregrasp_collision_free);
    FIELD(GraspResponse, warnings);
    FIELD(GraspResponse, reserved);

    TYPE(MethodStats, GRASPD_TYPE_NAME_METHOD_STATS);
    FIELD(MethodStats, name);
    FIELD(MethodStats, requests);
    FIELD(MethodStats, by_status);
    FIELD(MethodStats, slow);
    FIELD(MethodStats, latency_p50_us);
    FIELD(MethodStats, latency_p90_us);
    FIELD(MethodStats, latency_p99_us);
    FIELD(MethodStats, latency_max_us);
    FIELD(MethodStats, compute_p50_us);
    FIELD(MethodStats, compute_p99_us);
    FIELD(MethodStats, window);
    FIELD(MethodStats, in_flight);

    TYPE(StatsResponse, GRASPD_TYPE_NAME_STATS_RESPONSE);
    FIELD(StatsResponse, uptime_ns);
    FIELD(StatsResponse, rss_bytes);
    FIELD(StatsResponse, clients_connected);
    FIELD(StatsResponse, queued);
    FIELD(StatsResponse, method_count);
    FIELD(StatsResponse, methods);

    NUMBER(GRASPD_PROTOCOL_VERSION);
    NUMBER(GRASPD_NAME_LEN);
    NUMBER(GRASPD_MAX_KEYPOINTS);
    NUMBER(GRASPD_MAX_LATENT);
    NUMBER(GRASPD_MAX_CATEGORIES);
    NUMBER(GRASPD_MAX_JOINTS);
    NUMBER(GRASPD_MAX_METHODS);
    NUMBER(GRASPD_MESSAGE_LEN);
    NUMBER(GRASPD_FRAME_TEXT_LEN);
    NUMBER(GRASPD_METHOD_HEALTH);
    NUMBER(GRASPD_METHOD_LIST_CATEGORIES);
    NUMBER(GRASPD_METHOD_REGISTER);
    NUMBER(GRASPD_METHOD_GRASP);
    NUMBER(GRASPD_METHOD_STATS);
    NUMBER(GRASPD_STATUS_OK);
    NUMBER(GRASPD_STATUS_INVALID_ARGUMENT);
    NUMBER(GRASPD_STATUS_DEADLINE_EXCEEDED);
    NUMBER(GRASPD_STATUS_NOT_FOUND);
    NUMBER(GRASPD_STATUS_RESOURCE_EXHAUSTED);
    NUMBER(GRASPD_STATUS_FAILED_PRECONDITION);
    NUMBER(GRASPD_STATUS_INTERNAL);
    NUMBER(GRASPD_STATUS_UNAVAILABLE);
    NUMBER(GRASPD_FLAG_VIEWPOINT);
    NUMBER(GRASPD_FLAG_SECOND_VIEWPOINT);
    NUMBER(GRASPD_FLAGS_ALL);
    NUMBER(GRASPD_TABLE_MODE_AUTO);
    NUMBER(GRASPD_TABLE_MODE_NONE);
    NUMBER(GRASPD_TABLE_MODE_GIVEN);
    NUMBER(GRASPD_GRASP_WARNING_REGISTRATION_NOT_CONFIDENT);
    NUMBER(GRASPD_GRASP_WARNING_PREGRASP_IN_COLLISION);
    NUMBER(GRASPD_GRASP_WARNING_NO_TABLE_FRAME_NOT_Z_UP);
    NUMBER(GRASPD_VIEWPOINT_SOURCE_NONE);
    NUMBER(GRASPD_VIEWPOINT_SOURCE_GIVEN);
    NUMBER(GRASPD_VIEWPOINT_SOURCE_ESTIMATED);
    NUMBER(GRASPD_SERVING);
    NUMBER(GRASPD_DRAINING);
    NUMBER(GRASPD_WAITING_EVENT);
    NUMBER(GRASPD_WAITING_POLL);

    TEXT(GRASPD_VERSION_SEGMENT);
    TEXT(GRASPD_DEFAULT_PREFIX);
    TEXT(GRASPD_ATTRIBUTE_PROTOCOL_VERSION);
    TEXT(GRASPD_METHOD_HEALTH_NAME);
    TEXT(GRASPD_METHOD_LIST_CATEGORIES_NAME);
    TEXT(GRASPD_METHOD_REGISTER_NAME);
    TEXT(GRASPD_METHOD_GRASP_NAME);
    TEXT(GRASPD_METHOD_STATS_NAME);
    return 0;
}
