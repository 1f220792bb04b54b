/* A grainpipe stage written in C: example_c.porosity_profile, the porosity of every slice
 * of a phase image along an axis. It shows that the plugin ABI is usable without Rust.
 *
 * Build: cc -shared -fPIC -O2 -I ../../plugin-api/include -o libporosity_c.so porosity.c
 * Use:   pipe run pipeline.yaml --plugin-dir .   (or `plugins: [path/libporosity_c.so]`)
 *
 * The host hands parameters as canonical JSON with every declared key present, e.g.
 * {"axis":"z","pore_label":0}, so a few string searches are enough here; a real plugin
 * would use a JSON library. */
#include <stdio.h>
#include <string.h>
#include "grainpipe_plugin.h"

static const char METADATA[] =
    "{\"stages\":[{\"id\":\"example_c.porosity_profile\",\"version\":\"1.0.0\","
    "\"doc\":\"Porosity of every slice of a phase image normal to an axis, written in C.\","
    "\"params\":[{\"name\":\"axis\",\"ty\":\"one of x, y, z\",\"unit\":\"\",\"doc\":\"profile axis\",\"default\":\"z\"},"
    "{\"name\":\"pore_label\",\"ty\":\"integer 0..255\",\"unit\":\"\",\"doc\":\"pore label\",\"default\":0}],"
    "\"inputs\":[{\"name\":\"image\",\"kind\":\"PhaseImage\",\"doc\":\"segmented volume\",\"optional\":false}],"
    "\"outputs\":[{\"name\":\"profile\",\"kind\":\"Table\",\"doc\":\"position [m], porosity\",\"optional\":false}]}]}";

static GpStr metadata_json(void) { GpStr s = {(const uint8_t *)METADATA, sizeof(METADATA) - 1}; return s; }

/* Copies a GpStr into a NUL-terminated buffer (truncating). */
static void cstr(GpStr s, char *buf, size_t cap) {
    size_t n = s.len < cap - 1 ? s.len : cap - 1;
    memcpy(buf, s.ptr, n);
    buf[n] = 0;
}

static int fail(const GpHost *host, int code, const char *key, const char *msg) {
    host->set_error(host->ctx, gp_str(key), gp_str(msg));
    return code;
}

/* axis index from {"axis":"x|y|z"}, -1 if invalid */
static int parse_axis(const char *params) {
    const char *a = strstr(params, "\"axis\":\"");
    if (!a) return -1;
    a += 8;
    if (a[1] != '"') return -1;
    return a[0] == 'x' ? 0 : a[0] == 'y' ? 1 : a[0] == 'z' ? 2 : -1;
}

static int parse_label(const char *params) {
    const char *a = strstr(params, "\"pore_label\":");
    int v = -1;
    if (!a || sscanf(a + 13, "%d", &v) != 1 || v < 0 || v > 255) return -1;
    return v;
}

/* Reads three numbers after "key":[ in the metadata. */
static int triple(const char *meta, const char *key, double out[3]) {
    char pat[32];
    snprintf(pat, sizeof pat, "\"%s\":[", key);
    const char *p = strstr(meta, pat);
    return p && sscanf(p + strlen(pat), "%lf,%lf,%lf", &out[0], &out[1], &out[2]) == 3;
}

static int check_params(const char *params, const GpHost *host, int *axis, int *label) {
    *axis = parse_axis(params);
    if (*axis < 0) return fail(host, GP_INVALID_PARAM, "axis", "must be one of x, y, z");
    *label = parse_label(params);
    if (*label < 0) return fail(host, GP_INVALID_PARAM, "pore_label", "must be an integer label 0..255");
    return GP_OK;
}

static int32_t preflight(uint32_t stage, GpStr params_json, const GpArtifact *inputs, uint32_t n, const GpHost *host) {
    char params[512];
    int axis, label;
    (void)stage; (void)inputs; (void)n;
    cstr(params_json, params, sizeof params);
    int rc = check_params(params, host, &axis, &label);
    if (rc != GP_OK) return rc;
    host->set_preflight(host->ctx, gp_str("{\"memory_bytes\":0,\"outputs\":{}}"));
    return GP_OK;
}

static int32_t run(uint32_t stage, GpStr params_json, const GpArtifact *inputs, uint32_t n, const GpHost *host) {
    char params[512], meta[4096];
    int axis, label;
    (void)stage;
    cstr(params_json, params, sizeof params);
    int rc = check_params(params, host, &axis, &label);
    if (rc != GP_OK) return rc;
    if (n < 1) return fail(host, GP_INVALID_INPUT, "image", "not connected");
    const GpArtifact *img = &inputs[0];
    const GpArray *labels = NULL;
    for (uint32_t i = 0; i < img->n_arrays; i++)
        if (img->arrays[i].name.len == 6 && memcmp(img->arrays[i].name.ptr, "labels", 6) == 0) labels = &img->arrays[i];
    if (!labels || labels->dtype != GP_U8 || labels->ndim != 3)
        return fail(host, GP_INVALID_INPUT, "image", "no 3-D u8 `labels` array");
    /* shape is (nz, ny, nx); the host passes C-contiguous arrays */
    size_t dims[3] = {labels->shape[2], labels->shape[1], labels->shape[0]};
    double spacing[3], origin[3];
    cstr(img->meta_json, meta, sizeof meta);
    if (!triple(meta, "spacing", spacing) || !triple(meta, "origin", origin))
        return fail(host, GP_INVALID_INPUT, "image", "grid spacing/origin missing");
    const uint8_t *lab = (const uint8_t *)labels->data;
    size_t slices = dims[axis], per_slice = dims[0] * dims[1] * dims[2] / (slices ? slices : 1);

    if (host->set_output(host->ctx, gp_str("profile"), gp_str("Table"),
            gp_str("{\"name\":\"porosity_profile\",\"columns\":[{\"name\":\"position\",\"unit\":\"m\",\"dtype\":\"f64\"},"
                   "{\"name\":\"porosity\",\"unit\":\"1\",\"dtype\":\"f64\"}]}")) != 0)
        return fail(host, GP_FAILED, "", "host refused the output");
    double *pos = host->alloc_array(host->ctx, gp_str("profile"), gp_str("position"), GP_F64, 1, &slices);
    double *por = host->alloc_array(host->ctx, gp_str("profile"), gp_str("porosity"), GP_F64, 1, &slices);
    if (!pos || !por) return fail(host, GP_FAILED, "", "allocation refused");
    for (size_t z = 0; z < dims[2]; z++) {
        for (size_t y = 0; y < dims[1]; y++)
            for (size_t x = 0; x < dims[0]; x++) {
                size_t idx[3] = {x, y, z};
                if (lab[x + dims[0] * (y + dims[1] * z)] == label) por[idx[axis]] += 1.0;
            }
        if (host->progress(host->ctx, z + 1, dims[2])) return fail(host, GP_CANCELLED, "", "cancelled");
    }
    for (size_t i = 0; i < slices; i++) {
        pos[i] = origin[axis] + ((double)i + 0.5) * spacing[axis];
        por[i] /= (double)per_slice;
    }
    return GP_OK;
}

static const GpPluginVTable VTABLE = {sizeof(GpPluginVTable), GRAINPIPE_ABI_VERSION, metadata_json, preflight, run};

uint32_t grainpipe_abi_version(void) { return GRAINPIPE_ABI_VERSION; }
const GpPluginVTable *grainpipe_plugin_entry(const GpHost *host) { (void)host; return &VTABLE; }
