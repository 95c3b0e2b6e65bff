/* insn_count_plugin.c: a qemu TCG plugin (host side) that counts the guest instructions executed, to
 * cross-check the measuring harness's instruction counts (measure_main.c reads virtual time under
 * -icount; this counts instructions directly). At exit it writes the count, a decimal number, to
 * the file named by its argument:
 *     qemu-system-arm ... -plugin BUILD/qemu/insn_count_plugin.so,out=insns.txt[,profile=tbs.txt]
 * With profile=PATH it also writes one line per translated block, "start-address instructions
 * executions" (hexadecimal address; a block retranslated appears once per translation), from which
 * tools/bench_firmware_target.py --profile sums the instructions per function.
 * Written against qemu's plugin API version 1 (qemu 7.x; the API is C and stable within a version):
 * the few declarations it needs are below, so no qemu headers are needed to build it. */
#include <stddef.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

typedef uint64_t qemu_plugin_id_t;
struct qemu_info_t;
struct qemu_plugin_tb;
struct qemu_plugin_insn;
enum qemu_plugin_op { QEMU_PLUGIN_INLINE_ADD_U64 };
typedef void (*tb_trans_cb)(qemu_plugin_id_t id, struct qemu_plugin_tb *tb);
typedef void (*udata_cb)(qemu_plugin_id_t id, void *userdata);

void qemu_plugin_register_vcpu_tb_trans_cb(qemu_plugin_id_t id, tb_trans_cb cb);
size_t qemu_plugin_tb_n_insns(const struct qemu_plugin_tb *tb);
struct qemu_plugin_insn *qemu_plugin_tb_get_insn(const struct qemu_plugin_tb *tb, size_t idx);
void qemu_plugin_register_vcpu_insn_exec_inline(struct qemu_plugin_insn *insn, enum qemu_plugin_op op, void *ptr,
                                                uint64_t imm);
void qemu_plugin_register_atexit_cb(qemu_plugin_id_t id, udata_cb cb, void *userdata);
uint64_t qemu_plugin_tb_vaddr(const struct qemu_plugin_tb *tb);
void qemu_plugin_register_vcpu_tb_exec_inline(struct qemu_plugin_tb *tb, enum qemu_plugin_op op, void *ptr,
                                              uint64_t imm);

__attribute__((visibility("default"))) int qemu_plugin_version = 1;
__attribute__((visibility("default"))) int qemu_plugin_install(qemu_plugin_id_t id, const struct qemu_info_t *info,
                                                               int argc, char **argv);

static uint64_t executed;        /* one vCPU (the MPS2 boards have one core): no race */
static char out_path[4096], profile_path[4096];

/* one translated block of the profile; allocated one by one, so the inline counter's address stays */
typedef struct block {
    uint64_t vaddr, insns, executions;
    struct block *next;
} block;
static block *blocks;

/* every instruction of a new translation block adds 1 when it executes (inline: no callback) */
static void on_translate(qemu_plugin_id_t id, struct qemu_plugin_tb *tb)
{
    size_t i, n = qemu_plugin_tb_n_insns(tb);
    (void)id;
    for (i = 0; i < n; i++)
        qemu_plugin_register_vcpu_insn_exec_inline(qemu_plugin_tb_get_insn(tb, i), QEMU_PLUGIN_INLINE_ADD_U64,
                                                   &executed, 1);
    if (profile_path[0]) {
        block *b = calloc(1, sizeof *b);
        if (!b)
            return;      /* out of host memory: the profile misses this block, the total does not */
        b->vaddr = qemu_plugin_tb_vaddr(tb);
        b->insns = n;
        b->next = blocks;
        blocks = b;
        qemu_plugin_register_vcpu_tb_exec_inline(tb, QEMU_PLUGIN_INLINE_ADD_U64, &b->executions, 1);
    }
}

static void on_exit_write(qemu_plugin_id_t id, void *userdata)
{
    FILE *f = fopen(out_path, "w");
    (void)id;
    (void)userdata;
    const block *b;
    if (f) {
        fprintf(f, "%llu\n", (unsigned long long)executed);
        fclose(f);
    }
    if (profile_path[0] && (f = fopen(profile_path, "w")) != NULL) {
        for (b = blocks; b; b = b->next)
            if (b->executions)
                fprintf(f, "%llx %llu %llu\n", (unsigned long long)b->vaddr, (unsigned long long)b->insns,
                        (unsigned long long)b->executions);
        fclose(f);
    }
}

int qemu_plugin_install(qemu_plugin_id_t id, const struct qemu_info_t *info, int argc, char **argv)
{
    int i;
    (void)info;
    for (i = 0; i < argc; i++)
        if (strncmp(argv[i], "out=", 4) == 0 && strlen(argv[i] + 4) < sizeof out_path)
            strcpy(out_path, argv[i] + 4);
        else if (strncmp(argv[i], "profile=", 8) == 0 && strlen(argv[i] + 8) < sizeof profile_path)
            strcpy(profile_path, argv[i] + 8);
    if (!out_path[0]) {
        fprintf(stderr, "insn_count_plugin: give the output file: -plugin insn_count_plugin.so,out=PATH\n");
        return -1;
    }
    qemu_plugin_register_vcpu_tb_trans_cb(id, on_translate);
    qemu_plugin_register_atexit_cb(id, on_exit_write, NULL);
    return 0;
}
