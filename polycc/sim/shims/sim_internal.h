/* Private reset hooks of the host shim modules (called by shim_reset). */
#pragma once

void shimLogReset(void);
void shimCommanderReset(void);
void shimDebugReset(void);
