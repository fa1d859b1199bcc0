/* Private reset hooks of the host shim modules (called by shim_reset), and cross-module setters. */
#pragma once

void shimLogReset(void);
void shimCommanderReset(void);
void shimDebugReset(void);
void shimAppchannelReset(void);
void shimPlatformReset(void);
void shimRadiolinkReset(void);
void shimLogSetYaw(float roll_deg, float pitch_deg, float yaw_deg);
void shimAssertFailed(void); /* a firmware ASSERT: the motors stop for good, as assertFail() does */
void shimHlTaskRun(void);    /* a preemption point: the high-level task carries out a queued command (sim_commander.c) */
unsigned long shimTaskPriority(void);
