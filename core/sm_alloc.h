/* sm_alloc: the allocator setting for programs built on the library.
 *
 * Why: a match allocates and frees buffers of megabytes many times (each ZoomOut iteration
 * builds a nearest-neighbour index of its embedding: 26 MB for homer's final bijective
 * step, a 1 MiB product block per query thread). glibc serves blocks above its mmap
 * threshold (128 KiB at first, raised dynamically only up to the largest block freed so
 * far) with fresh mappings, and trims the top of its heap above 128 KiB of free space, so
 * those buffers came back as new pages every time: page faults and the kernel's zeroing
 * were 9% of homer's match in a perf profile, and with the daemon's other threads at work
 * each fault also waits for the process's memory map lock.
 *
 * sm_alloc_keep_large keeps blocks up to SM_ALLOC_MMAP_MAX in the heap (glibc's ceiling
 * for that threshold on 64-bit) and trims only beyond SM_ALLOC_TRIM of free top space, so
 * a freed buffer is reused by the next iteration. The cost is resident memory: each
 * thread's arena keeps up to the peak of what it freed (a match's peak, tens of MB).
 *
 * Contract: process-wide state (mallopt). Call once at the start of main, before other
 * threads exist; core never calls it itself. Returns 0, or -1 when the C library does not
 * take the settings (not glibc): nothing changed then, the program runs as before.
 */
#ifndef SM_ALLOC_H
#define SM_ALLOC_H

#define SM_ALLOC_MMAP_MAX (32 << 20)
#define SM_ALLOC_TRIM (256 << 20)

int sm_alloc_keep_large(void);

#endif
