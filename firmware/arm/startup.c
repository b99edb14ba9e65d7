/* Reset handler and vector table of the Cortex-M test programs (not part of the library):
 * copy .data, clear .bss, enable the FPU on a Cortex-M4F, run main, end the emulation. */
#include <stdint.h>

#include "semihost.h"

extern uint32_t _sidata, _sdata, _edata, _sbss, _ebss, _estack;
int main(void);

void Reset_Handler(void);
void Fault_Handler(void);

void Reset_Handler(void)
{
    uint32_t *src = &_sidata, *dst;
    for (dst = &_sdata; dst < &_edata; ++dst) *dst = *src++;
    for (dst = &_sbss; dst < &_ebss; ++dst) *dst = 0u;
#if defined(__ARM_FP)
    /* CPACR: full access to CP10 and CP11 (the FPU) before any floating-point instruction */
    *(volatile uint32_t *)0xE000ED88u |= 0xFu << 20;
    __asm__ __volatile__("dsb\n\tisb" ::: "memory");
#endif
    sh_exit(main() == 0);
}

void Fault_Handler(void)
{
    sh_puts("fault\n");
    sh_exit(0);
}

/* Initial stack pointer, reset, NMI, HardFault, MemManage, BusFault, UsageFault. */
__attribute__((section(".isr_vector"), used)) const uintptr_t vectors[7] = {
    (uintptr_t)&_estack,       (uintptr_t)Reset_Handler, (uintptr_t)Fault_Handler,
    (uintptr_t)Fault_Handler, (uintptr_t)Fault_Handler, (uintptr_t)Fault_Handler,
    (uintptr_t)Fault_Handler,
};
