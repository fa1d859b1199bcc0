/*
 * polycc_shim.h -- the host side of the firmware API shims, for Python (cffi) and tests.
 *
 * Log and parameter tables: every LOG_GROUP_START..LOG_GROUP_STOP and PARAM_GROUP_START..
 * PARAM_GROUP_STOP block compiled with POLYCC_SHIM_HOST registers itself at load time.
 * Groups are kept sorted by name (stable), variables in declaration order, so the TOC is
 * deterministic.  Index i of shim_log_entry() is the logVarId_t that logGetVarId() returns.
 */
#ifndef POLYCC_SHIM_H
#define POLYCC_SHIM_H

#include <stddef.h>
#include <stdint.h>

typedef struct shim_toc_entry {
    const char *group;       /* group name */
    const char *name;        /* variable name */
    uint8_t type;            /* the firmware's type byte (LOG_* with LOG_CORE/LOG_BY_FUNCTION bits, or PARAM_* bits) */
    uint8_t extended_type;   /* params: the extended type byte (PARAM_PERSISTENT >> 8); logs: 0 */
    void *address;           /* the variable */
    void (*callback)(void);  /* params: called after a write (may be NULL); logs: NULL */
} shim_toc_entry_t;

/* Log TOC. */
int shim_log_count(void);
int shim_log_entry(int index, shim_toc_entry_t *out); /* 0, or -1 if index is out of range */
double shim_log_value(int index);                     /* current value as a double (NaN if out of range) */

/* Parameter TOC. */
int shim_param_count(void);
int shim_param_entry(int index, shim_toc_entry_t *out);
int shim_param_index(const char *group, const char *name); /* -1 when absent */
double shim_param_value(int index);
/* Writes value converted to the parameter's type (integers truncated toward zero and
 * clamped to the type's range), then calls its callback.  0, -1 bad index, -2 read-only. */
int shim_param_set(int index, double value);

/* Size in bytes of a log or param type byte's value (0 if unknown). */
int shim_log_type_size(uint8_t type);
int shim_param_type_size(uint8_t type);

/* Simulated time.  shim_reset() also clears the commander record and the debug buffer. */
void shim_reset(void);
void shim_set_tick(uint32_t tick); /* FreeRTOS tick (1 ms) */
uint32_t shim_get_tick(void);
/* usecTimestamp() returns now_us; the read after it returns now_us + section_us (the cycle
 * model of the code between two consecutive reads), later reads keep that value. */
void shim_set_usec(uint64_t now_us, uint32_t section_us);

/* Simulated state estimate: backs the log groups stateEstimate (x, y, z, vx, vy, vz) and
 * kalman (varX, varY, varZ).  shim_set_kalman_present(0) hides the kalman group from
 * logGetVarId (as with another estimator). */
void shim_set_estimate(float x, float y, float z, float vx, float vy, float vz);
void shim_set_position_variance(float var_x, float var_y, float var_z);
void shim_set_kalman_present(int present);
void shim_set_estimate_present(int present);

/* Commander record. */
typedef struct shim_commander_record {
    uint32_t count;          /* setpoints accepted since reset */
    uint32_t rejected;       /* setpoints below the active priority */
    uint32_t relax_count;    /* commanderRelaxPriority() calls */
    uint32_t tick;           /* shim tick of the last accepted setpoint */
    int priority;            /* priority of the last accepted setpoint */
    int active_priority;     /* current priority (COMMANDER_PRIORITY_LOWEST after a relax) */
    int mode_x, mode_y, mode_z, mode_roll, mode_pitch, mode_yaw; /* stab_mode_t values */
    int velocity_body;       /* 1 body frame, 0 world frame */
    float vx, vy, vz;        /* m/s */
    float px, py, pz;        /* m (position setpoints) */
    float yaw_rate;          /* deg/s */
    int hl_state;            /* high-level planner: 0 idle (stopped), 1 flying, 2 landing */
    int hl_takeoffs, hl_lands, hl_gotos, hl_stops; /* calls of the high-level commander's API */
} shim_commander_record_t;
/* The last setpoint with priority above HIGHLEVEL (the app's or a client's), and the
 * high-level commander's state. */
void shim_commander_get(shim_commander_record_t *out);

/* One stabilizer step (call once per 1 ms tick, after shim_set_tick): the high-level commander at
 * 100 Hz, the commander's choice and the supervisor's setpoint watchdog, as the firmware's
 * stabilizer loop does.  ``out`` is the setpoint the controller gets; motors_on is 0 for the null
 * setpoint (the motors stop). */
typedef struct shim_setpoint {
    int motors_on;
    int mode_x, mode_y, mode_z, mode_roll, mode_pitch, mode_yaw; /* stab_mode_t */
    int velocity_body;
    float px, py, pz;     /* m */
    float vx, vy, vz;     /* m/s */
    float ax, ay, az;     /* m/s^2 (feed-forward) */
    float roll, pitch, yaw; /* deg */
    float yaw_rate;       /* deg/s */
    float thrust;
    int priority;         /* the commander's active priority */
    uint32_t age_ms;      /* age of the commander's setpoint */
} shim_setpoint_t;
void shim_stabilizer_step(const float pos[3], const float vel[3], float yaw_deg, shim_setpoint_t *out);
/* The estimate's acceleration (m/s^2, world frame; state->acc in Gs) the next stabilizer steps report. */
void shim_set_acceleration(float ax, float ay, float az);
/* controllerPid() calls (made by the out-of-tree controller while it is selected). */
uint32_t shim_pid_calls(void);
/* A client's setpoint at a commander priority (motors_on = 0: the stop setpoint), and cflib's
 * notify_setpoint_stop. */
void shim_commander_set(const shim_setpoint_t *sp, int priority);
void shim_commander_notify_stop(int remain_ms);
/* As after a finished high-level takeoff: hovering at (x, y, z) under the high-level commander. */
void shim_hl_hover_at(float x, float y, float z);
/* A land (absolute height m, duration s) from the ground, carried out by the high-level commander's task at the
 * worst instant for the app: its packet arrives just after the app's next check of the planner
 * (crtpCommanderHighLevelIsStopped), and the task (CMD_HIGH_LEVEL_TASK_PRI) carries it out at the first
 * preemption point after that check at which the app's task runs below that priority: a call into the
 * commander or the high-level commander, a priority change.  shim_hl_run_pending(): the app's task sleeps (end
 * of its tick), so a queued land is carried out now; 1 if one was. */
void shim_hl_queue_land(float height, float duration);
int shim_hl_run_pending(void);
int shim_motors_on(void);

/* Supervisor, controller and link (as the firmware reports them to apps). */
void shim_set_supervisor(int is_locked, int is_crashed, int is_tumbled);
void shim_set_controller(int type); /* ControllerType; also written by the param stabilizer.controller */
void shim_set_connected(int is_connected);

/* App channel: packets from the ground (push) and the app's replies (pop); 0 when empty. */
int shim_appchannel_push(const void *data, size_t length);
size_t shim_appchannel_pop(void *buffer, size_t max_length);
/* App-channel sends longer than the CRTP payload (30 bytes): the firmware ASSERTs (motors off, reset). */
int shim_crtp_asserts(void);

/* P2P radio (radiolink.h): the app's broadcasts, oldest first, as raw bytes (port, then data; 0 when none),
 * and a packet another drone broadcast (raw: port, then data) handed to the app's P2P callback (-1: no
 * callback registered or a bad length); broadcasts lost to a full queue. */
size_t shim_p2p_pop(void *buffer, size_t max_length);
int shim_p2p_deliver(const void *raw, size_t length, int rssi);
int shim_p2p_lost(void);

/* Attitude and thrust of the simulated vehicle (log stateEstimate.roll/pitch/yaw, stabilizer.*). */
void shim_set_attitude(float roll_deg, float pitch_deg, float yaw_deg, float thrust);
/* The PID position controller's z integral output (log posCtl.Zi, m/s), and its gains as the params
 * posCtlPid.zKp (which 0, 1/s) and zKi (which 1, 1/s^2) hold them. */
void shim_set_position_integrator(float zi);
float shim_position_gain(int which);

/* DEBUG_PRINT output since the last read (NUL-terminated, truncated to n-1 bytes). */
size_t shim_debug_read(char *buf, size_t n);

#endif /* POLYCC_SHIM_H */
