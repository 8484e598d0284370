/* A C host of the aggtool runtime: opens an .agg, makes its own pinhole camera, traces a
 * batch of cones per sample through the C ABI and writes the image as a PFM (linear RGB).
 *
 *   cc -O2 -Iintegrations/c/include integrations/c/examples/host.c \
 *      -Ltarget/release -laggtool_capi -lm -o host
 *   LD_LIBRARY_PATH=target/release ./host FILE.agg OUT.pfm [W H SPP EX EY EZ TX TY TZ FOV]
 *
 * The camera is the view file's: eye, target, up +y, vertical field of view in degrees, row 0
 * at the top, right = forward x up (so `aggtool render --view` with the same numbers renders
 * the same picture, up to Monte Carlo noise). It also exercises the error paths: a missing
 * file and null arguments must come back as error codes with a message. */
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "aggtool.h"

static void normalize(float v[3]) {
    float l = sqrtf(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]);
    for (int i = 0; i < 3; i++) v[i] /= l;
}

static void cross(const float a[3], const float b[3], float out[3]) {
    out[0] = a[1] * b[2] - a[2] * b[1];
    out[1] = a[2] * b[0] - a[0] * b[2];
    out[2] = a[0] * b[1] - a[1] * b[0];
}

/* The host's own random numbers: xorshift64*. */
static float next(uint64_t *s) {
    *s ^= *s >> 12;
    *s ^= *s << 25;
    *s ^= *s >> 27;
    return (float)((*s * 0x2545F4914F6CDD1DULL) >> 40) / 16777216.0f;
}

int main(int argc, char **argv) {
    if (argc < 3) {
        fprintf(stderr, "usage: %s FILE.agg OUT.pfm [W H SPP EX EY EZ TX TY TZ FOV]\n", argv[0]);
        return 2;
    }
    if (agg_abi_version() != AGG_ABI_VERSION) {
        fprintf(stderr, "ABI %u, header %u\n", agg_abi_version(), AGG_ABI_VERSION);
        return 1;
    }
    /* Bad input is an error code and a message, never a crash. */
    if (agg_open("/nonexistent/missing.agg") != NULL || strlen(agg_last_error()) == 0) {
        fprintf(stderr, "a missing file was not refused\n");
        return 1;
    }
    if (agg_bounds(NULL, NULL, NULL) != AGG_ERR_ARGUMENT) {
        fprintf(stderr, "null arguments were not refused\n");
        return 1;
    }
    AggScene *scene = agg_open(argv[1]);
    if (!scene) {
        fprintf(stderr, "agg_open: %s\n", agg_last_error());
        return 1;
    }
    uint32_t w = argc > 3 ? (uint32_t)atoi(argv[3]) : 64;
    uint32_t h = argc > 4 ? (uint32_t)atoi(argv[4]) : 64;
    uint32_t spp = argc > 5 ? (uint32_t)atoi(argv[5]) : 16;
    float lo[3], hi[3], eye[3], target[3], fov = 40.0f;
    if (agg_bounds(scene, lo, hi) != AGG_OK) {
        fprintf(stderr, "agg_bounds: %s\n", agg_last_error());
        return 1;
    }
    if (argc > 12) {
        for (int i = 0; i < 3; i++) {
            eye[i] = (float)atof(argv[6 + i]);
            target[i] = (float)atof(argv[9 + i]);
        }
        fov = (float)atof(argv[12]);
    } else {
        float r = 0.0f;
        for (int i = 0; i < 3; i++) {
            target[i] = 0.5f * (lo[i] + hi[i]);
            r += (hi[i] - lo[i]) * (hi[i] - lo[i]);
        }
        r = 0.5f * sqrtf(r);
        float d[3] = {0.3f, 0.35f, 1.0f};
        normalize(d);
        for (int i = 0; i < 3; i++) eye[i] = target[i] + d[i] * 2.5f * r;
    }
    float fwd[3] = {target[0] - eye[0], target[1] - eye[1], target[2] - eye[2]};
    normalize(fwd);
    float up0[3] = {0.0f, 1.0f, 0.0f}, right[3], up[3];
    cross(fwd, up0, right);
    normalize(right);
    cross(right, fwd, up);
    float tan_half = tanf(fov * 3.14159265f / 360.0f), aspect = (float)w / (float)h;
    float aperture = 2.0f * tan_half / (float)h;

    AggLights *lights = agg_lights_new();
    size_t n = (size_t)w * h;
    AggCone *cones = malloc(n * sizeof(AggCone));
    float *rgba = malloc(n * 4 * sizeof(float));
    float *sum = calloc(n * 3, sizeof(float));
    uint64_t rng = 0x9E3779B97F4A7C15ULL;
    for (uint32_t s = 0; s < spp; s++) {
        for (uint32_t y = 0; y < h; y++) {
            for (uint32_t x = 0; x < w; x++) {
                float px = ((float)x + next(&rng)) / (float)w * 2.0f - 1.0f;
                float py = 1.0f - ((float)y + next(&rng)) / (float)h * 2.0f;
                AggCone *c = &cones[y * w + x];
                for (int i = 0; i < 3; i++) {
                    c->origin[i] = eye[i];
                    c->dir[i] = fwd[i] + px * tan_half * aspect * right[i] + py * tan_half * up[i];
                }
                c->aperture = aperture;
            }
        }
        if (agg_trace_cones(scene, lights, cones, n, 1000 + s, rgba) != AGG_OK) {
            fprintf(stderr, "agg_trace_cones: %s\n", agg_last_error());
            return 1;
        }
        for (size_t i = 0; i < n; i++)
            for (int k = 0; k < 3; k++) sum[3 * i + k] += rgba[4 * i + k] / (float)spp;
    }
    /* One hit list, through the traversal layer: the hits' weights and the transmittance. */
    AggHit hits[256];
    size_t count = 0;
    float trans = 0.0f;
    AggCone centre = {{eye[0], eye[1], eye[2]}, {fwd[0], fwd[1], fwd[2]}, aperture};
    if (agg_hits(scene, &centre, hits, 256, &count, &trans) != AGG_OK) {
        fprintf(stderr, "agg_hits: %s\n", agg_last_error());
        return 1;
    }
    if (count > 0) {
        float rgb[3], wi[3] = {0.0f, 1.0f, 0.0f}, wo[3] = {-fwd[0], -fwd[1], -fwd[2]};
        if (agg_voxel_eval(scene, hits[0].level, hits[0].key, wi, wo, rgb) != AGG_OK) {
            fprintf(stderr, "agg_voxel_eval: %s\n", agg_last_error());
            return 1;
        }
    }
    FILE *f = fopen(argv[2], "wb");
    if (!f) {
        perror(argv[2]);
        return 1;
    }
    fprintf(f, "PF\n%u %u\n-1.0\n", w, h);
    for (uint32_t y = h; y-- > 0;) fwrite(&sum[3 * (size_t)y * w], sizeof(float), 3 * (size_t)w, f);
    fclose(f);
    double mean = 0.0;
    for (size_t i = 0; i < 3 * n; i++) mean += sum[i];
    printf("host.c: %ux%u at %u spp, mean %.4f; centre cone: %zu hits, transmittance %.3f\n", w, h,
           spp, mean / (3.0 * (double)n), count, trans);
    free(cones);
    free(rgba);
    free(sum);
    agg_lights_free(lights);
    agg_close(scene);
    return 0;
}
