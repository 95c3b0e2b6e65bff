/* virtual_clock.h: the time sources of the emulated MPS2 boards, read by the measuring harness.
 *
 * qemu-system-arm -icount shift=S runs the guest at exactly 2^S virtual ns per instruction, and the
 * boards' counters advance with that virtual time, so a counter difference is an instruction count:
 *   instructions = ticks * (1e9 / f_counter) / 2^S      (f_counter in Hz, 1e9 / f in ns per tick)
 * The counter is read as floor(virtual ns * f / 1e9), so one difference is exact to +-1 tick
 * (1e9 / f / 2^S instructions: 40 for AN386's 25 MHz counter at S = 0, 50 for AN505's 20 MHz).
 *
 * Primary: the FPGAIO COUNTER, 32 bits, counting up at the FPGA prescale clock while PRESCALE = 0
 * (its reset value): 0x40028000 + 0x18 on AN386 (Cortex-M4F), the secure alias 0x50302000 + 0x18 on
 * AN505 (Cortex-M33, run in secure state). It wraps after 2^32 ticks (>= 171 s of virtual time).
 * Cross-check: SysTick (architectural, 24 bits, counting down at the processor clock when
 * CLKSOURCE = 1); on real silicon it counts core cycles instead of instructions. */
#ifndef MKC_VIRTUAL_CLOCK_H
#define MKC_VIRTUAL_CLOCK_H

#include <stdint.h>

#if defined(__ARM_ARCH_8M_MAIN__)
#define MKC_FPGAIO_BASE 0x50302000u   /* AN505 */
#else
#define MKC_FPGAIO_BASE 0x40028000u   /* AN385/AN386 */
#endif
#define MKC_FPGAIO_COUNTER (*(volatile uint32_t *)(MKC_FPGAIO_BASE + 0x18u))

#define MKC_SYST_CSR (*(volatile uint32_t *)0xE000E010u)
#define MKC_SYST_RVR (*(volatile uint32_t *)0xE000E014u)
#define MKC_SYST_CVR (*(volatile uint32_t *)0xE000E018u)
#define MKC_SYST_MASK 0x00FFFFFFu

/* SysTick free-running from its full 24-bit reload, processor clock, no interrupt. */
static inline void mkc_systick_start(void)
{
    MKC_SYST_CSR = 0u;
    MKC_SYST_RVR = MKC_SYST_MASK;
    MKC_SYST_CVR = 0u;          /* any write clears the count; it reloads on the next tick */
    MKC_SYST_CSR = 5u;          /* ENABLE | CLKSOURCE (processor clock), TICKINT off */
}

#endif /* MKC_VIRTUAL_CLOCK_H */
