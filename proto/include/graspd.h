/*
 * graspd.h: the graspd service contract for C (C11) and C++ (C++17).
 *
 * The message types of `graspd serve`, byte for byte as proto/src/lib.rs
 * defines them, with the constants, status codes and iceoryx2 type names a
 * client needs. proto/README.md is the reference for each field's meaning,
 * unit and frame, the services and the calling sequence; this header only
 * spares a C or C++ client from retyping the layouts. The test
 * proto/tests/c_header.rs compiles it as C and as C++ and compares every
 * field's offset and size, every constant and every type name with the
 * Rust definition.
 *
 * In C++ each message type carries `static constexpr const char*
 * IOX2_TYPE_NAME`, the name iceoryx2's C++ bindings register it under, so the
 * types can be given to the service builder directly, e.g. for Register:
 * request payload a slice of graspd_Point, response payload
 * graspd_RegisterResponse, request user header graspd_RequestHeader,
 * response user header graspd_ResponseHeader. In C, pass the
 * GRASPD_TYPE_NAME_* strings with sizeof and alignof of the type to
 * iox2_service_builder_request_response_set_*_type_details (the cloud:
 * iox2_type_variant_e_DYNAMIC with graspd_Point's name, size and alignment).
 *
 * Conventions: SI units (metres, radians, nanoseconds unless a name says
 * _us), quaternions (x, y, z, w), little-endian, native alignment, no
 * implicit padding. Text fields hold UTF-8 padded with NUL bytes; a text
 * filling its whole field has no terminator (copy with a length limit).
 */
#ifndef GRASPD_H
#define GRASPD_H

#include <stddef.h>
#include <stdint.h>

/* ---------------------------------------------------------------------------
 * Version, service names
 * ------------------------------------------------------------------------- */

/* RequestHeader::protocol_version must equal this; the type names and the
 * service names carry it too ("graspd.v4.*", "<prefix>/v4/<method>"). */
#define GRASPD_PROTOCOL_VERSION 4u
#define GRASPD_VERSION_SEGMENT "v4"
#define GRASPD_DEFAULT_PREFIX "graspd"

/* Request-response service of a method: "<prefix>/v4/<method name>";
 * its paired event service: "<prefix>/v4/<method name>/notify";
 * a client's reply event service: "<prefix>/v4/reply/<token as 16 lower-case
 * hex digits>" (see RequestHeader::notify_token). */
#define GRASPD_METHOD_HEALTH_NAME "health"
#define GRASPD_METHOD_LIST_CATEGORIES_NAME "list_categories"
#define GRASPD_METHOD_REGISTER_NAME "register"
#define GRASPD_METHOD_GRASP_NAME "grasp"
#define GRASPD_METHOD_STATS_NAME "stats"

/* Method indices: the index of a method in StatsResponse::methods. */
#define GRASPD_METHOD_HEALTH 0u
#define GRASPD_METHOD_LIST_CATEGORIES 1u
#define GRASPD_METHOD_REGISTER 2u
#define GRASPD_METHOD_GRASP 3u
#define GRASPD_METHOD_STATS 4u

/* Attribute the daemon sets on every request-response service; its value is
 * GRASPD_PROTOCOL_VERSION in decimal. */
#define GRASPD_ATTRIBUTE_PROTOCOL_VERSION "graspd.protocol_version"

/* ---------------------------------------------------------------------------
 * Sizes of fixed arrays
 * ------------------------------------------------------------------------- */

#define GRASPD_NAME_LEN 32
#define GRASPD_MAX_KEYPOINTS 8
#define GRASPD_MAX_LATENT 16
#define GRASPD_MAX_CATEGORIES 8
#define GRASPD_MAX_JOINTS 16
#define GRASPD_MAX_METHODS 8
#define GRASPD_MESSAGE_LEN 128
#define GRASPD_FRAME_TEXT_LEN 384

/* ---------------------------------------------------------------------------
 * Values of u32 fields
 * ------------------------------------------------------------------------- */

/* ResponseHeader::status: gRPC's numeric codes. Treat an unknown value as
 * INTERNAL (a newer daemon's code). */
#define GRASPD_STATUS_OK 0u
#define GRASPD_STATUS_INVALID_ARGUMENT 3u
#define GRASPD_STATUS_DEADLINE_EXCEEDED 4u
#define GRASPD_STATUS_NOT_FOUND 5u
#define GRASPD_STATUS_RESOURCE_EXHAUSTED 8u
#define GRASPD_STATUS_FAILED_PRECONDITION 9u
#define GRASPD_STATUS_INTERNAL 13u
#define GRASPD_STATUS_UNAVAILABLE 14u

/* RequestHeader::flags bits; unknown bits are refused (INVALID_ARGUMENT). */
#define GRASPD_FLAG_VIEWPOINT 1u
#define GRASPD_FLAG_SECOND_VIEWPOINT 2u /* needs GRASPD_FLAG_VIEWPOINT */
#define GRASPD_FLAGS_ALL 3u

/* RequestHeader::table_mode. */
#define GRASPD_TABLE_MODE_AUTO 0u
#define GRASPD_TABLE_MODE_NONE 1u
#define GRASPD_TABLE_MODE_GIVEN 2u

/* GraspResponse::warnings bits. */
#define GRASPD_GRASP_WARNING_REGISTRATION_NOT_CONFIDENT 1u
#define GRASPD_GRASP_WARNING_PREGRASP_IN_COLLISION 2u
#define GRASPD_GRASP_WARNING_NO_TABLE_FRAME_NOT_Z_UP 4u

/* Registration::viewpoint_source. */
#define GRASPD_VIEWPOINT_SOURCE_NONE 0u
#define GRASPD_VIEWPOINT_SOURCE_GIVEN 1u
#define GRASPD_VIEWPOINT_SOURCE_ESTIMATED 2u

/* HealthResponse::serving. */
#define GRASPD_SERVING 1u
#define GRASPD_DRAINING 2u

/* HealthResponse::waiting. */
#define GRASPD_WAITING_EVENT 0u
#define GRASPD_WAITING_POLL 1u

/* ---------------------------------------------------------------------------
 * iceoryx2 type names (each with the type's size and alignment identifies
 * it to iceoryx2; a service opened with another type fails)
 * ------------------------------------------------------------------------- */

#define GRASPD_TYPE_NAME_REQUEST_HEADER "graspd.v4.RequestHeader"
#define GRASPD_TYPE_NAME_POINT "graspd.v4.Point"
#define GRASPD_TYPE_NAME_NO_PAYLOAD "graspd.v4.NoPayload"
#define GRASPD_TYPE_NAME_RESPONSE_HEADER "graspd.v4.ResponseHeader"
#define GRASPD_TYPE_NAME_HEALTH_RESPONSE "graspd.v4.HealthResponse"
#define GRASPD_TYPE_NAME_CATEGORY_INFO "graspd.v4.CategoryInfo"
#define GRASPD_TYPE_NAME_CATEGORIES_RESPONSE "graspd.v4.CategoriesResponse"
#define GRASPD_TYPE_NAME_KEYPOINT "graspd.v4.Keypoint"
#define GRASPD_TYPE_NAME_REGISTRATION "graspd.v4.Registration"
#define GRASPD_TYPE_NAME_REGISTER_RESPONSE "graspd.v4.RegisterResponse"
#define GRASPD_TYPE_NAME_HAND_CONFIGURATION "graspd.v4.HandConfiguration"
#define GRASPD_TYPE_NAME_GRASP_RESPONSE "graspd.v4.GraspResponse"
#define GRASPD_TYPE_NAME_METHOD_STATS "graspd.v4.MethodStats"
#define GRASPD_TYPE_NAME_STATS_RESPONSE "graspd.v4.StatsResponse"

/* In C++, the type name iceoryx2's bindings read; nothing in C. */
#ifdef __cplusplus
#define GRASPD_IOX2_TYPE_NAME(name) static constexpr const char* IOX2_TYPE_NAME = name;
#else
#define GRASPD_IOX2_TYPE_NAME(name)
#endif

/* ---------------------------------------------------------------------------
 * Messages
 * ------------------------------------------------------------------------- */

/* The request user header of every method (160 bytes). */
typedef struct graspd_RequestHeader {
    GRASPD_IOX2_TYPE_NAME(GRASPD_TYPE_NAME_REQUEST_HEADER)
    uint64_t request_id;       /* chosen by the client, echoed in the response */
    uint64_t deadline_unix_ns; /* absolute, CLOCK_REALTIME; 0 = none */
    uint64_t notify_token;     /* non-zero: the daemon notifies <prefix>/v4/reply/<token> after responding */
    uint64_t seed;             /* seed of the registration's randomised parts */
    uint32_t protocol_version; /* GRASPD_PROTOCOL_VERSION */
    uint32_t flags;            /* GRASPD_FLAG_* */
    char category[GRASPD_NAME_LEN];    /* Register, Grasp: "mug", "drill", "hammer" (ListCategories) */
    char cloud_frame[GRASPD_NAME_LEN]; /* free text, echoed; points and result poses are in this frame */
    float up_in_cloud[3];              /* world up in the cloud's frame, any length; 0 = unknown */
    uint32_t table_mode;               /* GRASPD_TABLE_MODE_* */
    float table_z_m;                   /* TABLE_MODE_GIVEN: table top height in the cloud's frame */
    float pregrasp_backoff_m;          /* Grasp: 0 = daemon default */
    float pregrasp_joint_fraction;     /* Grasp: in (0, 1]; 0 = daemon default */
    float viewpoint_in_cloud_m[3];     /* with GRASPD_FLAG_VIEWPOINT: the camera's origin in the cloud's frame */
    float second_viewpoint_in_cloud_m[3]; /* with GRASPD_FLAG_SECOND_VIEWPOINT: a second camera's, the cloud merging both views */
    uint32_t reserved;                 /* must be 0 */
} graspd_RequestHeader;

/* One point of a cloud, metres, in the request's cloud_frame (12 bytes, the
 * layout of float[3]). Register and Grasp take a slice of them. */
typedef struct graspd_Point {
    GRASPD_IOX2_TYPE_NAME(GRASPD_TYPE_NAME_POINT)
    float xyz[3];
} graspd_Point;

/* The request payload of Health, ListCategories and Stats (8 bytes). */
typedef struct graspd_NoPayload {
    GRASPD_IOX2_TYPE_NAME(GRASPD_TYPE_NAME_NO_PAYLOAD)
    uint64_t reserved;
} graspd_NoPayload;

/* The response user header of every method (160 bytes). The body is
 * meaningful only when status is GRASPD_STATUS_OK. */
typedef struct graspd_ResponseHeader {
    GRASPD_IOX2_TYPE_NAME(GRASPD_TYPE_NAME_RESPONSE_HEADER)
    uint64_t request_id;       /* the request's request_id */
    uint64_t server_ns;        /* receipt to response in the daemon, queueing included */
    uint64_t compute_ns;       /* the engine's work; round trip minus this = transport overhead */
    uint32_t status;           /* GRASPD_STATUS_* */
    uint32_t protocol_version; /* the daemon's */
    char message[GRASPD_MESSAGE_LEN]; /* detail of a non-OK status */
} graspd_ResponseHeader;

/* Health response body (120 bytes). */
typedef struct graspd_HealthResponse {
    GRASPD_IOX2_TYPE_NAME(GRASPD_TYPE_NAME_HEALTH_RESPONSE)
    uint64_t uptime_ns;
    uint64_t startup_ns; /* process start to serving */
    uint32_t pid;
    uint32_t protocol_version;
    uint32_t serving; /* GRASPD_SERVING, GRASPD_DRAINING */
    uint32_t waiting; /* GRASPD_WAITING_EVENT: notify the method's event service after sending */
    uint32_t categories;
    uint32_t max_points; /* largest cloud accepted */
    uint32_t max_in_flight_per_client;
    uint32_t workers;
    uint32_t grasp_available;      /* 1 when Grasp serves at least one category */
    uint32_t hand_actuated_joints; /* of the hand Grasp solves for; 0: no hand */
    char server_version[GRASPD_NAME_LEN];
    char hand_name[GRASPD_NAME_LEN]; /* the hand's URDF robot name; empty: no hand */
} graspd_HealthResponse;

/* One category the daemon serves (688 bytes). */
typedef struct graspd_CategoryInfo {
    GRASPD_IOX2_TYPE_NAME(GRASPD_TYPE_NAME_CATEGORY_INFO)
    char name[GRASPD_NAME_LEN]; /* the value for RequestHeader::category */
    uint32_t latent_dim;
    uint32_t keypoint_count;
    char keypoint_names[GRASPD_MAX_KEYPOINTS][GRASPD_NAME_LEN]; /* in Register's order */
    char canonical_frame[GRASPD_FRAME_TEXT_LEN];                /* the canonical frame in words */
    uint32_t grasp_available; /* 1 when Grasp serves this category */
    uint32_t reserved;
} graspd_CategoryInfo;

/* ListCategories response body (5512 bytes, alignment 4). */
typedef struct graspd_CategoriesResponse {
    GRASPD_IOX2_TYPE_NAME(GRASPD_TYPE_NAME_CATEGORIES_RESPONSE)
    uint32_t count; /* entries used in categories */
    uint32_t reserved;
    graspd_CategoryInfo categories[GRASPD_MAX_CATEGORIES];
} graspd_CategoriesResponse;

/* A transferred keypoint (56 bytes). */
typedef struct graspd_Keypoint {
    GRASPD_IOX2_TYPE_NAME(GRASPD_TYPE_NAME_KEYPOINT)
    char name[GRASPD_NAME_LEN];
    double position_cloud_m[3];
} graspd_Keypoint;

/* A registration of a category's shape space to a cloud (768 bytes).
 * p_cloud = R (scale p_canonical) + t. */
typedef struct graspd_Registration {
    GRASPD_IOX2_TYPE_NAME(GRASPD_TYPE_NAME_REGISTRATION)
    double latent[GRASPD_MAX_LATENT]; /* first latent_dim used */
    double rotation_cloud_from_canonical_xyzw[4];
    double translation_cloud_from_canonical_m[3];
    double scale;
    double sigma2_m2;
    double inlier_fraction;
    double residual_m;
    double inlier_threshold_m;
    double viewpoint_cloud_m[3]; /* the camera position the fit used; 0 when viewpoint_source is NONE */
    double coverage;             /* share of the completed shape's surface the view shows */
    double view_width_m;
    double latent_mahalanobis;    /* standard deviations outside the family */
    double contradicted_fraction; /* -1 when not assessed */
    uint32_t latent_dim;
    uint32_t keypoint_count;
    uint32_t confident;      /* 1: the fit explains the cloud and the cloud shows enough of a tool */
    uint32_t points;         /* received in the request */
    uint32_t ambiguous_pose; /* 1: another pose at least 30 degrees away explains the view almost as well */
    uint32_t stray_points;   /* set aside before the fit */
    uint32_t viewpoint_source;  /* GRASPD_VIEWPOINT_SOURCE_* */
    float yaw_half_width_rad;   /* turns about the upright axis that explain the view as well; -1 not assessed */
    uint32_t table_points;      /* of stray_points, the table a leaking segmentation included */
    uint32_t reserved;
    graspd_Keypoint keypoints[GRASPD_MAX_KEYPOINTS]; /* first keypoint_count used */
} graspd_Registration;

/* Register response body (768 bytes). */
typedef struct graspd_RegisterResponse {
    GRASPD_IOX2_TYPE_NAME(GRASPD_TYPE_NAME_REGISTER_RESPONSE)
    graspd_Registration registration;
} graspd_RegisterResponse;

/* A hand configuration: wrist (palm root link) pose and joints (312 bytes). */
typedef struct graspd_HandConfiguration {
    GRASPD_IOX2_TYPE_NAME(GRASPD_TYPE_NAME_HAND_CONFIGURATION)
    double rotation_cloud_from_wrist_xyzw[4];
    double translation_cloud_from_wrist_m[3];
    double actuated[GRASPD_MAX_JOINTS]; /* order GraspResponse::actuated_names; rad or m */
    double joints[GRASPD_MAX_JOINTS];   /* every moving joint, order GraspResponse::joint_names */
} graspd_HandConfiguration;

/* Grasp response body: registration, grasp and pre-grasp (2488 bytes). */
typedef struct graspd_GraspResponse {
    GRASPD_IOX2_TYPE_NAME(GRASPD_TYPE_NAME_GRASP_RESPONSE)
    graspd_Registration registration;
    graspd_HandConfiguration grasp;
    graspd_HandConfiguration pregrasp;
    char actuated_names[GRASPD_MAX_JOINTS][GRASPD_NAME_LEN];
    char joint_names[GRASPD_MAX_JOINTS][GRASPD_NAME_LEN];
    double task_space_distance_m;
    double residual_mean_m;
    double residual_max_m;
    double penetration_m;
    double pregrasp_min_clearance_m; /* negative: penetration */
    double table_z_m;                /* when table_used */
    uint32_t actuated_count;
    uint32_t joint_count;
    uint32_t table_used;
    uint32_t pregrasp_collision_free;
    uint32_t warnings; /* GRASPD_GRASP_WARNING_* */
    uint32_t reserved;
} graspd_GraspResponse;

/* Counters and latencies of one method (232 bytes). */
typedef struct graspd_MethodStats {
    GRASPD_IOX2_TYPE_NAME(GRASPD_TYPE_NAME_METHOD_STATS)
    char name[GRASPD_NAME_LEN];
    uint64_t requests;
    uint64_t by_status[16]; /* index: status code */
    uint64_t slow;
    double latency_p50_us;
    double latency_p90_us;
    double latency_p99_us;
    double latency_max_us;
    double compute_p50_us;
    double compute_p99_us;
    uint32_t window;
    uint32_t in_flight;
} graspd_MethodStats;

/* Stats response body (1888 bytes). */
typedef struct graspd_StatsResponse {
    GRASPD_IOX2_TYPE_NAME(GRASPD_TYPE_NAME_STATS_RESPONSE)
    uint64_t uptime_ns;
    uint64_t rss_bytes;
    uint64_t clients_connected;
    uint32_t queued;
    uint32_t method_count;
    graspd_MethodStats methods[GRASPD_MAX_METHODS]; /* index: GRASPD_METHOD_* */
} graspd_StatsResponse;

/* ---------------------------------------------------------------------------
 * The sizes proto/README.md documents, checked where the header is compiled
 * ------------------------------------------------------------------------- */

#ifdef __cplusplus
#define GRASPD_STATIC_ASSERT(cond, msg) static_assert(cond, msg)
#else
#define GRASPD_STATIC_ASSERT(cond, msg) _Static_assert(cond, msg)
#endif

GRASPD_STATIC_ASSERT(sizeof(graspd_RequestHeader) == 160, "RequestHeader is 160 bytes");
GRASPD_STATIC_ASSERT(sizeof(graspd_Point) == 12, "Point is 12 bytes");
GRASPD_STATIC_ASSERT(sizeof(graspd_NoPayload) == 8, "NoPayload is 8 bytes");
GRASPD_STATIC_ASSERT(sizeof(graspd_ResponseHeader) == 160, "ResponseHeader is 160 bytes");
GRASPD_STATIC_ASSERT(sizeof(graspd_HealthResponse) == 120, "HealthResponse is 120 bytes");
GRASPD_STATIC_ASSERT(sizeof(graspd_CategoryInfo) == 688, "CategoryInfo is 688 bytes");
GRASPD_STATIC_ASSERT(sizeof(graspd_CategoriesResponse) == 5512, "CategoriesResponse is 5512 bytes");
GRASPD_STATIC_ASSERT(sizeof(graspd_Keypoint) == 56, "Keypoint is 56 bytes");
GRASPD_STATIC_ASSERT(sizeof(graspd_Registration) == 768, "Registration is 768 bytes");
GRASPD_STATIC_ASSERT(offsetof(graspd_Registration, keypoints) == 320, "Registration::keypoints at 320");
GRASPD_STATIC_ASSERT(sizeof(graspd_HandConfiguration) == 312, "HandConfiguration is 312 bytes");
GRASPD_STATIC_ASSERT(sizeof(graspd_GraspResponse) == 2488, "GraspResponse is 2488 bytes");
GRASPD_STATIC_ASSERT(sizeof(graspd_MethodStats) == 232, "MethodStats is 232 bytes");
GRASPD_STATIC_ASSERT(sizeof(graspd_StatsResponse) == 1888, "StatsResponse is 1888 bytes");

#undef GRASPD_STATIC_ASSERT

#endif /* GRASPD_H */
