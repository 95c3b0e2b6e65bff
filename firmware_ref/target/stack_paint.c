/* stack_paint.c: stack painting and the high-water scan (see stack_paint.h). */
#include "stack_paint.h"

/* noinline: its frame sits above the stack pointer it reads, so painting below that pointer never
 * overwrites a word it still uses (no interrupt is enabled while it runs). */
__attribute__((noinline)) uint32_t mkc_stack_paint(uint32_t *low)
{
    uint32_t *sp = mkc_stack_pointer(), *p;
    uint32_t words = 0;
    for (p = low; p < sp; p++, words++)
        *(volatile uint32_t *)p = MKC_STACK_PATTERN;
    return words;
}

uint32_t *mkc_stack_deepest(uint32_t *low, uint32_t *high)
{
    uint32_t *p = low;
    while (p < high && *p == MKC_STACK_PATTERN)
        p++;
    return p;
}
