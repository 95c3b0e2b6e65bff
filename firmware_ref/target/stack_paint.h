/* stack_paint.h: stack high-water mark by painting. The unused stack below the caller is filled with
 * a pattern; after the code under test has run, the lowest word that no longer holds the pattern is
 * the deepest the stack reached (a word the code wrote with the pattern's value itself would be
 * missed: one chance in 2^32 per word). */
#ifndef MKC_STACK_PAINT_H
#define MKC_STACK_PAINT_H

#include <stdint.h>

#define MKC_STACK_PATTERN 0xC5A3E1F7u

/* The current stack pointer. */
static inline uint32_t *mkc_stack_pointer(void)
{
    uint32_t *sp;
    __asm__ volatile("mov %0, sp" : "=r"(sp));
    return sp;
}

/* Fills every word from low up to this call's own stack pointer with MKC_STACK_PATTERN; returns the
 * number of words painted (0 when low is not below the stack pointer). */
uint32_t mkc_stack_paint(uint32_t *low);
/* The lowest address in [low, high) whose word is not the pattern; high when every word still is. */
uint32_t *mkc_stack_deepest(uint32_t *low, uint32_t *high);

#endif /* MKC_STACK_PAINT_H */
