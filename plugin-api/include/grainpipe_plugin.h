/* grainpipe plugin C ABI, version 1.0. Mirrors plugin-api/src/lib.rs (the #[repr(C)] types).
 *
 * A plugin is a shared library exporting:
 *   uint32_t grainpipe_abi_version(void);                       (major << 16) | minor
 *   const GpPluginVTable *grainpipe_plugin_entry(const GpHost *host);
 * The host refuses a library whose major version differs from its own.
 * Metadata and parameters cross as UTF-8 JSON; arrays as borrowed views; output arrays are
 * allocated by the host (alloc_array) and owned by it. See docs/PLUGINS.md. */
#ifndef GRAINPIPE_PLUGIN_H
#define GRAINPIPE_PLUGIN_H

#include <stddef.h>
#include <stdint.h>

#define GRAINPIPE_ABI_MAJOR 1u
#define GRAINPIPE_ABI_MINOR 0u
#define GRAINPIPE_ABI_VERSION ((GRAINPIPE_ABI_MAJOR << 16) | GRAINPIPE_ABI_MINOR)

/* status codes */
#define GP_OK 0
#define GP_INVALID_PARAM 1 /* set_error key = parameter name */
#define GP_INVALID_INPUT 2 /* set_error key = port name */
#define GP_FAILED 3
#define GP_CANCELLED 4
#define GP_PANIC 5

/* dtypes */
#define GP_U8 1u
#define GP_U32 2u
#define GP_I64 3u
#define GP_F32 4u
#define GP_F64 5u

typedef struct GpStr { const uint8_t *ptr; size_t len; } GpStr; /* UTF-8, not NUL-terminated */

typedef struct GpArray {
    GpStr name;
    uint32_t dtype;
    uint32_t ndim;
    const size_t *shape;
    const intptr_t *strides; /* bytes */
    const void *data;
} GpArray;

typedef struct GpArtifact {
    GpStr port;
    GpStr kind;      /* "PhaseImage", "Field", "Table", "Tensor", "Packing" */
    GpStr meta_json; /* grid, phase table, units, columns, ... */
    uint32_t n_arrays;
    const GpArray *arrays;
} GpArtifact;

typedef struct GpHost {
    uint32_t struct_size;
    void *ctx;
    void (*set_error)(void *ctx, GpStr key, GpStr message);
    void (*set_preflight)(void *ctx, GpStr json);
    int32_t (*set_output)(void *ctx, GpStr port, GpStr kind, GpStr meta_json);
    void *(*alloc_array)(void *ctx, GpStr port, GpStr name, uint32_t dtype, uint32_t ndim, const size_t *shape);
    int32_t (*progress)(void *ctx, uint64_t done, uint64_t total); /* returns 1 to stop */
    void (*log)(void *ctx, int32_t level, GpStr message);
} GpHost;

typedef struct GpPluginVTable {
    uint32_t struct_size;
    uint32_t abi_version;
    GpStr (*metadata_json)(void);
    int32_t (*preflight)(uint32_t stage, GpStr params_json, const GpArtifact *inputs, uint32_t n_inputs, const GpHost *host);
    int32_t (*run)(uint32_t stage, GpStr params_json, const GpArtifact *inputs, uint32_t n_inputs, const GpHost *host);
} GpPluginVTable;

static inline GpStr gp_str(const char *s) {
    size_t n = 0;
    while (s[n]) n++;
    GpStr r = {(const uint8_t *)s, n};
    return r;
}

#endif
