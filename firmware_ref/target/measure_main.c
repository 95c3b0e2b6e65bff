/* measure_main.c: what the calibrator costs on the emulated Cortex-M: the stack high-water mark of a
 * whole replay (stack painting) and the instructions of every mkc_mag_push (a virtual-time counter
 * under qemu-system-arm -icount, virtual_clock.h). tools/bench_firmware_target.py runs it.
 *
 * Input: mkc_in.bin, as the replay harness (replay_input.h). Output:
 * - mkc_cost.bin: per sample two little-endian uint32: the counter ticks of that push, and flags
 *   (COST_ESTEP: an E-step ran; COST_CHECKPOINT: a checkpoint ran). Read and written outside the
 *   timed interval, which holds only the call (and the conversion of its three arguments).
 * - one console line "MKC_MEASURE key=value ..." (all values unsigned decimal):
 *     samples, checkpoints, esteps          the replay
 *     ticks_sum, worst_ticks, worst_sample  per-push ticks summed, the largest, its sample (1-based)
 *     worst_flags                           that sample's flags
 *     empty_ticks                           an empty timed interval (the timing's own cost)
 *     loop_a_iters, loop_a_ticks, loop_b_iters, loop_b_ticks, systick_b_ticks
 *                                           calibration: a 2-instruction loop of a and b iterations
 *                                           timed by the counter, and b again by SysTick
 *     stack_call_bytes                      deepest stack below the replay loop's frame: the calls it
 *                                           makes (mkc_mag_push and the harness's small I/O calls)
 *     stack_top_bytes                       deepest stack below the initial stack pointer
 *     stack_painted_bytes                   the painted (checked) region below the loop's frame
 *     stack_overflow                        1 when the deepest word is the painted region's bottom
 *     state_bytes                           sizeof(mkc_mag_t)
 *     clock_end_ticks                       the counter at the end (ticks since the board's reset: the
 *                                           whole run, to compare with an instruction-counting plugin)
 * Exit status 0, 1 for unreadable input or a write error, 2 for a configuration the library refuses.
 */
#include <stdint.h>

#include "mkc.h"
#include "mkc_target_io.h"
#include "replay_input.h"
#include "stack_paint.h"
#include "virtual_clock.h"

enum { COST_ESTEP = 1, COST_CHECKPOINT = 2 };

#define PAINT_BYTES 65536u          /* the checked stack region below the replay loop's frame */
#define LOOP_A 50000u               /* calibration loop lengths (iterations of 2 instructions) */
#define LOOP_B 250000u

extern uint32_t _ebss[], _stack_top[];

static mkc_mag_t cal;                           /* the state: static, never on the stack */
static double block[3 * MKC_IN_BLOCK];          /* static too: the stack holds only the calls */
static uint32_t cost[2 * MKC_IN_BLOCK];
static char line[1024];

/* ticks of the FPGAIO counter over `iterations` passes of a 2-instruction loop (subs, bne) */
__attribute__((noinline)) static uint32_t counter_loop(uint32_t iterations)
{
    uint32_t t0 = MKC_FPGAIO_COUNTER, t1;
    __asm__ volatile("1: subs %0, %0, #1\n\tbne 1b" : "+r"(iterations) : : "cc");
    t1 = MKC_FPGAIO_COUNTER;
    return t1 - t0;
}

/* the same loop timed by SysTick (counting down) */
__attribute__((noinline)) static uint32_t systick_loop(uint32_t iterations)
{
    uint32_t t0 = MKC_SYST_CVR, t1;
    __asm__ volatile("1: subs %0, %0, #1\n\tbne 1b" : "+r"(iterations) : : "cc");
    t1 = MKC_SYST_CVR;
    return (t0 - t1) & MKC_SYST_MASK;
}

/* appends " key=value" to line (1024 bytes hold twice the keys printed; a key that did not fit would
 * be missing, which tools/bench_firmware_target.py reports as an error) */
static void put(const char *key, uint64_t value)
{
    char digits[24];
    size_t n = 0, at = 0;
    while (line[at])
        at++;
    if (at + 48 > sizeof line)
        return;
    line[at++] = ' ';
    while (*key)
        line[at++] = *key++;
    line[at++] = '=';
    do {
        digits[n++] = (char)('0' + (int)(value % 10u));
        value /= 10u;
    } while (value);
    while (n)
        line[at++] = digits[--n];
    line[at] = '\0';
}

int main(void)
{
    uint32_t *frame = mkc_stack_pointer(), *low = frame - PAINT_BYTES / 4u, *deepest;
    uint64_t ticks_sum = 0;
    uint32_t worst = 0, worst_flags = 0, empty, loop_a, loop_b, sys_b, clock_end;
    int32_t T, done = 0, worst_sample = 0;
    int64_t checkpoints0;
    mkc_mag_config cfg;
    int in, out, failed = 0;

    if (low < _ebss) {
        mkc_io_console("mkc measure: RAM too small for the painted stack region\n");
        return 1;
    }
    (void)mkc_stack_paint(low);
    mkc_systick_start();
    loop_a = counter_loop(LOOP_A);
    loop_b = counter_loop(LOOP_B);
    sys_b = systick_loop(LOOP_B);
    {
        uint32_t t0 = MKC_FPGAIO_COUNTER;
        empty = MKC_FPGAIO_COUNTER - t0;
    }

    in = mkc_replay_open_input(&cfg, &T);
    if (in < 0)
        return 1;
    if (mkc_mag_init(&cal, &cfg) != MKC_OK) {
        mkc_io_console("mkc measure: the library refuses the configuration\n");
        return 2;
    }
    out = mkc_io_open("mkc_cost.bin", 1);
    if (out < 0) {
        mkc_io_console("mkc measure: cannot write mkc_cost.bin\n");
        return 1;
    }
    checkpoints0 = cal.checkpoints;
    while (done < T) {
        int32_t n = T - done < MKC_IN_BLOCK ? T - done : MKC_IN_BLOCK, k;
        if (mkc_replay_read_block(in, block, n) != 0)
            return 1;
        for (k = 0; k < n; k++) {
            int64_t esteps = cal.core.counters.esteps, checkpoints = cal.checkpoints;
            uint32_t t0, t1, flags;
            t0 = MKC_FPGAIO_COUNTER;
            (void)mkc_mag_push(&cal, (mkc_real)block[3 * k], (mkc_real)block[3 * k + 1], (mkc_real)block[3 * k + 2]);
            t1 = MKC_FPGAIO_COUNTER;
            flags = (cal.core.counters.esteps != esteps ? COST_ESTEP : 0u)
                  | (cal.checkpoints != checkpoints ? COST_CHECKPOINT : 0u);
            cost[2 * k] = t1 - t0;
            cost[2 * k + 1] = flags;
            ticks_sum += t1 - t0;
            if (t1 - t0 > worst) {
                worst = t1 - t0;
                worst_sample = done + k + 1;
                worst_flags = flags;
            }
        }
        if (mkc_io_write(out, cost, (size_t)n * 2 * sizeof(uint32_t)) != (long)((size_t)n * 2 * sizeof(uint32_t)))
            failed = 1;
        done += n;
    }
    mkc_io_close(in);
    mkc_io_close(out);
    deepest = mkc_stack_deepest(low, frame);
    clock_end = MKC_FPGAIO_COUNTER;

    put("samples", (uint64_t)T);
    put("checkpoints", (uint64_t)(cal.checkpoints - checkpoints0));
    put("esteps", (uint64_t)cal.core.counters.esteps);
    put("ticks_sum", ticks_sum);
    put("worst_ticks", worst);
    put("worst_sample", (uint64_t)worst_sample);
    put("worst_flags", worst_flags);
    put("empty_ticks", empty);
    put("loop_a_iters", LOOP_A);
    put("loop_a_ticks", loop_a);
    put("loop_b_iters", LOOP_B);
    put("loop_b_ticks", loop_b);
    put("systick_b_ticks", sys_b);
    put("stack_call_bytes", (uint64_t)(frame - deepest) * 4u);
    put("stack_top_bytes", (uint64_t)(_stack_top - deepest) * 4u);
    put("stack_painted_bytes", PAINT_BYTES);
    put("stack_overflow", deepest == low ? 1u : 0u);
    put("state_bytes", sizeof(mkc_mag_t));
    put("clock_end_ticks", clock_end);
    mkc_io_console("MKC_MEASURE");
    mkc_io_console(line);
    mkc_io_console(failed ? "\nmkc measure: write error\n" : "\nmkc measure: done\n");
    return failed;
}
