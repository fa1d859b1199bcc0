/* Shim of the setpoint and state types of crazyflie-firmware src/modules/interface/stabilizer_types.h
 * (same field names, types and order for the members declared here). */
#pragma once

#include <stdbool.h>
#include <stdint.h>

/* Number of stabilizer loop runs (1 kHz). */
typedef uint32_t stabilizerStep_t;
/* Opaque here: the app only passes them on to controllerPid(). */
typedef struct control_s control_t;
typedef struct sensorData_s sensorData_t;

typedef struct attitude_s {
    uint32_t timestamp;
    float roll;  /* deg */
    float pitch; /* deg */
    float yaw;   /* deg */
} attitude_t;

struct vec3_s {
    uint32_t timestamp;
    float x;
    float y;
    float z;
};
typedef struct vec3_s vector_t;
typedef struct vec3_s point_t;
typedef struct vec3_s velocity_t;
typedef struct vec3_s acc_t;
typedef struct vec3_s jerk_t;

typedef struct quaternion_s {
    union {
        struct {
            float q0;
            float q1;
            float q2;
            float q3;
        };
        struct {
            float x;
            float y;
            float z;
            float w;
        };
    };
} quaternion_t;

typedef struct state_s {
    attitude_t attitude;
    quaternion_t attitudeQuaternion;
    point_t position;    /* m */
    velocity_t velocity; /* m/s */
    acc_t acc;           /* Gs */
} state_t;

typedef enum mode_e {
    modeDisable = 0,
    modeAbs,
    modeVelocity
} stab_mode_t;

typedef struct {
    stab_mode_t x;
    stab_mode_t y;
    stab_mode_t z;
    stab_mode_t roll;
    stab_mode_t pitch;
    stab_mode_t yaw;
    stab_mode_t quat;
} setpoint_mode_t;

typedef struct setpoint_s {
    uint32_t timestamp;
    attitude_t attitude;     /* deg */
    attitude_t attitudeRate; /* deg/s */
    quaternion_t attitudeQuaternion;
    float thrust;
    point_t position;     /* m */
    velocity_t velocity;  /* m/s */
    acc_t acceleration;   /* m/s^2 */
    jerk_t jerk;          /* m/s^3 */
    bool velocity_body;   /* true: body frame, false: world frame */
    setpoint_mode_t mode;
} setpoint_t;
