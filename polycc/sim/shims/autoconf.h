/* Host shim of the firmware's generated Kconfig header (build/include/generated/autoconf.h): the
 * symbols of firmware_app/app-config that the app's C reads. */
#ifndef POLYCC_SHIM_AUTOCONF_H
#define POLYCC_SHIM_AUTOCONF_H
#ifndef CONFIG_CONTROLLER_OOT
#define CONFIG_CONTROLLER_OOT 1
#endif
#endif
