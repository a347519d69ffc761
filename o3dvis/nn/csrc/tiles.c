/* The AMX tiles, which the view margins' MLP (mlp.c) and the convolutions (conv.c) run on: whether
 * the operating system grants them, and their configuration. */

#include "kernels.h"

#ifdef __AMX_BF16__
#include <sys/syscall.h>
#include <unistd.h>

/* Whether the operating system lets this process use the AMX tiles (Linux grants their state to a
   process that asks; kernels before 5.16 cannot): asked once a process, threads that race here
   ask twice and get the same answer. */
int tiles_granted(void) {
    static int granted = -1;
    if (__atomic_load_n(&granted, __ATOMIC_RELAXED) < 0)
        __atomic_store_n(&granted, syscall(SYS_arch_prctl, 0x1023 /* ARCH_REQ_XCOMP_PERM */,
                                           18 /* XFEATURE_XTILEDATA */) == 0, __ATOMIC_RELAXED);
    return __atomic_load_n(&granted, __ATOMIC_RELAXED);
}

/* Eight tiles of 16 rows of 64 bytes. For the MLP, tiles 0-3: the sums of 16 outputs x 16 points of
   four groups (float32); 4: 16 outputs x 16 pairs of weights; 5 and 6: 16 pairs of inputs x 16
   points. For o3dvis_gather_conv, see conv_block. */
__attribute__((target("amx-tile"))) void configure_tiles(void) {
    struct { uint8_t palette, start_row, reserved[14]; uint16_t colsb[16]; uint8_t rows[16]; } config = {1, 0, {0},
                                                                                                     {0}, {0}};
    for (int i = 0; i < 8; i++) config.colsb[i] = 64, config.rows[i] = 16;
    _tile_loadconfig(&config);
}

__attribute__((target("amx-tile"))) void release_tiles(void) { _tile_release(); }

#endif
