/* startup.c: reset for the emulated MPS2 boards: copy .data, zero .bss, enable the FPU, run main,
 * exit through semihosting. The vector table holds the initial stack pointer and the handlers; any
 * fault exits with status 1 (qemu then exits non-zero) instead of hanging. */
#include <stdint.h>

extern uint32_t _sidata[], _sdata[], _edata[], _sbss[], _ebss[], _stack_top[];
int main(void);
void mkc_target_exit(int status);
void mkc_reset_handler(void);

static void fault_handler(void)
{
    mkc_target_exit(1);
}

void mkc_reset_handler(void)
{
    uint32_t *src = _sidata, *dst;
    for (dst = _sdata; dst < _edata;)
        *dst++ = *src++;
    for (dst = _sbss; dst < _ebss;)
        *dst++ = 0;
#if defined(__ARM_FP)
    /* CPACR: full access to coprocessors 10 and 11 (the FPU) before any floating-point instruction */
    *(volatile uint32_t *)0xE000ED88u |= 0xFu << 20;
    __asm__ volatile("dsb\n\tisb" ::: "memory");
#endif
    mkc_target_exit(main());
}

typedef union vector {
    void (*handler)(void);
    uint32_t *stack;
} vector;

/* initial SP, reset, NMI, HardFault, MemManage, BusFault, UsageFault, SecureFault (M33) */
__attribute__((section(".vectors"), used)) static const vector vectors[8] = {
    {.stack = _stack_top},      {.handler = mkc_reset_handler}, {.handler = fault_handler}, {.handler = fault_handler},
    {.handler = fault_handler}, {.handler = fault_handler}, {.handler = fault_handler}, {.handler = fault_handler}};
