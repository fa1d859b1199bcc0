/* ARM image for bench_swarm.py --arm: keeps polycc_step and polycc_swarm_step linked; the benchmark
 * calls them directly in the Cortex-M4 model (bench_kernel.Emulator), main never runs them. */
#include "polycc_swarm.h"

volatile int polycc_bench_never;

int main(void)
{
    if (polycc_bench_never) {
        static polycc_swarm_t sw;
        static polycc_out_t out;
        static const float x[3] = {0.0f, 0.0f, 0.0f};
        (void)polycc_swarm_step(0, 0, &sw, 1.0f, x, x, &out);
        (void)polycc_step(0, 0, x, x, &out);
    }
    return 0;
}
