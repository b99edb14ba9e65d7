/* Cycle profile of one function of an ATmega128 program under simavr (a host tool, not part of
 * the library; needs Debian's libsimavr-dev).
 *
 *   gcc -O2 firmware/avr/profile.c -I/usr/include/simavr -lsimavr -o profile
 *   avr-nm -n cycles.elf > cycles.sym
 *   ./profile cycles.elf cycles.sym anchor_step_gnss [atmega1284p]   (default core atmega128)
 *
 * Runs the program instruction by instruction (simavr's cycle counts), and while `function` is
 * active (from its entry to the return to its caller, calls included) adds each instruction's
 * cycles to the symbol it belongs to. Prints, per call of `function`: its mean cycles, and for
 * each symbol the cycles spent in it (its own instructions: self time) and how often it was
 * entered. The program's own UART output is printed by simavr as it runs. */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include <sim_avr.h>
#include <sim_elf.h>

#define MAX_SYMS 4096
#define FLASH_WORDS 65536u /* ATmega128: 128 KB of flash */

static unsigned sym_addr[MAX_SYMS];
static char sym_name[MAX_SYMS][64];
static unsigned long long word_cycles[FLASH_WORDS], word_count[FLASH_WORDS];

int main(int argc, char **argv)
{
    elf_firmware_t fw;
    avr_t *avr;
    FILE *f;
    char line[256];
    int n_sym = 0, i, state = cpu_Running, inside = 0;
    unsigned entry = 0xffffffffu, sp0 = 0, ret = 0, p;
    unsigned long long calls = 0, total = 0, start = 0;
    if (argc != 4 && argc != 5) {
        fprintf(stderr, "usage: %s program.elf symbols.txt function [mcu]\n", argv[0]);
        return 2;
    }
    f = fopen(argv[2], "r");
    if (!f) {
        perror(argv[2]);
        return 2;
    }
    while (fgets(line, sizeof line, f) && n_sym < MAX_SYMS) {
        unsigned a;
        char type, name[64];
        if (sscanf(line, "%x %c %63s", &a, &type, name) == 3 && (type == 'T' || type == 't') && a < 0x800000u) {
            sym_addr[n_sym] = a;
            snprintf(sym_name[n_sym], sizeof sym_name[n_sym], "%s", name);
            if (!strcmp(name, argv[3])) entry = a;
            ++n_sym;
        }
    }
    fclose(f);
    if (entry == 0xffffffffu) {
        fprintf(stderr, "%s: no function %s\n", argv[2], argv[3]);
        return 2;
    }
    memset(&fw, 0, sizeof fw);
    if (elf_read_firmware(argv[1], &fw) != 0) {
        fprintf(stderr, "%s: cannot read\n", argv[1]);
        return 2;
    }
    avr = avr_make_mcu_by_name(argc > 4 ? argv[4] : "atmega128"); /* optional 4th argument: the core */
    avr_init(avr);
    avr_load_firmware(avr, &fw);
    avr->frequency = 8000000;
    while (state != cpu_Done && state != cpu_Crashed) {
        avr_flashaddr_t pc = avr->pc;
        avr_cycle_count_t c0 = avr->cycle;
        unsigned sp = avr->data[0x5d] | (avr->data[0x5e] << 8); /* SPL, SPH */
        if (!inside && pc == entry) {
            /* the return address the call pushed (big-endian word address above SP) */
            inside = 1;
            sp0 = sp;
            ret = 2u * ((unsigned)(avr->data[sp + 1] << 8) | avr->data[sp + 2]);
            start = c0;
            ++calls;
        } else if (inside && pc == ret && sp == sp0 + 2) {
            /* back in the caller (SP compared too: a frame's SP is written in two halves) */
            inside = 0;
            total += c0 - start;
        }
        state = avr_run(avr);
        if (inside && pc / 2 < FLASH_WORDS) {
            word_cycles[pc / 2] += avr->cycle - c0;
            word_count[pc / 2] += 1;
        }
    }
    if (calls == 0) {
        printf("%s was never called\n", argv[3]);
        return 1;
    }
    printf("%s: %llu calls, %.0f cycles per call\n", argv[3], calls, (double)total / (double)calls);
    printf("%12s %10s  symbol (per call: cycles in its own instructions, entries)\n", "cycles", "entries");
    for (i = 0; i < n_sym; ++i) {
        unsigned long long c = 0;
        unsigned end = i + 1 < n_sym ? sym_addr[i + 1] : 2u * FLASH_WORDS;
        for (p = sym_addr[i] / 2; p < end / 2 && p < FLASH_WORDS; ++p) c += word_cycles[p];
        if (c > 0) {
            printf("%12.1f %10.2f  %s\n", (double)c / (double)calls,
                   (double)word_count[sym_addr[i] / 2] / (double)calls, sym_name[i]);
        }
    }
    return 0;
}
