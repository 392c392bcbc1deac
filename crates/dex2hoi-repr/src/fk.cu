// Forward kinematics on a GPU, one thread per frame: the CUDA side of `FkOp` (`fk.rs`), the
// same recursion `G_j = G_p R_j`, `p_j = p_p + G_p o_j` and its backward pass
// `dR_j = G_p^T dG_j`, `dG_p += dG_j R_j^T + dp_j o_j^T`, `dp_p += dp_j`, with the products
// summed in the order of the CPU's loops. Compiled at run time by NVRTC (`fk_cuda.rs`).
//
// Layouts (all contiguous f32): local rotations [batch, joints, 9] (row-major 3x3), roots
// [batch, 3], parents [joints] (-1 for the root; a parent precedes its children), rest offsets
// [samples, joints, 3] (frame f uses sample f / frames_per_sample; frames_per_sample 0: one set
// for every frame), and a scratch of [batch, joints, 12] per pass: each joint's global rotation
// (9) and position (3), or in the backward pass their gradients.

__device__ void forward_frame(const float* local, const float* root, const int* parents,
                              const float* offsets, unsigned int joints, float* packed) {
    for (unsigned int j = 0; j < joints; j++) {
        const float* r = local + j * 9;
        float* g = packed + j * 12;
        int p = parents[j];
        if (p < 0) {
            for (int k = 0; k < 9; k++) g[k] = r[k];
            for (int i = 0; i < 3; i++) g[9 + i] = root[i];
            continue;
        }
        const float* gp = packed + p * 12;
        const float* o = offsets + j * 3;
        for (int i = 0; i < 3; i++) {
            for (int c = 0; c < 3; c++) {
                g[i * 3 + c] = gp[i * 3] * r[c] + gp[i * 3 + 1] * r[3 + c] + gp[i * 3 + 2] * r[6 + c];
            }
            g[9 + i] = gp[9 + i] + (gp[i * 3] * o[0] + gp[i * 3 + 1] * o[1] + gp[i * 3 + 2] * o[2]);
        }
    }
}

__device__ const float* offsets_of(const float* offsets, unsigned int frame,
                                   unsigned int frames_per_sample, unsigned int joints) {
    unsigned int sample = frames_per_sample ? frame / frames_per_sample : 0;
    return offsets + (size_t)sample * joints * 3;
}

// out [batch, joints, width] = the part [from, from + width) of each joint's 12 numbers.
extern "C" __global__ void fk_forward_f32(const float* local, const float* root,
                                          const int* parents, const float* offsets,
                                          unsigned int frames_per_sample, unsigned int joints,
                                          unsigned int batch, float* packed, float* out,
                                          unsigned int width, unsigned int from) {
    unsigned int frame = blockIdx.x * blockDim.x + threadIdx.x;
    if (frame >= batch) return;
    float* state = packed + (size_t)frame * joints * 12;
    forward_frame(local + (size_t)frame * joints * 9, root + (size_t)frame * 3, parents,
                  offsets_of(offsets, frame, frames_per_sample, joints), joints, state);
    float* frame_out = out + (size_t)frame * joints * width;
    for (unsigned int j = 0; j < joints; j++) {
        for (unsigned int k = 0; k < width; k++) frame_out[j * width + k] = state[j * 12 + from + k];
    }
}

// grad_local [batch, joints, 9] from the gradient `grad` of the positions (width 3) or of the
// rotations (width 9).
extern "C" __global__ void fk_backward_f32(const float* local, const float* root,
                                           const int* parents, const float* offsets,
                                           unsigned int frames_per_sample, unsigned int joints,
                                           unsigned int batch, float* packed, float* state,
                                           const float* grad, unsigned int width,
                                           float* grad_local) {
    unsigned int frame = blockIdx.x * blockDim.x + threadIdx.x;
    if (frame >= batch) return;
    const float* frame_local = local + (size_t)frame * joints * 9;
    const float* o = offsets_of(offsets, frame, frames_per_sample, joints);
    float* globals = packed + (size_t)frame * joints * 12;
    forward_frame(frame_local, root + (size_t)frame * 3, parents, o, joints, globals);
    float* d = state + (size_t)frame * joints * 12;
    const float* frame_grad = grad + (size_t)frame * joints * width;
    for (unsigned int j = 0; j < joints; j++) {
        for (int k = 0; k < 12; k++) d[j * 12 + k] = 0.0f;
        unsigned int at = width == 3 ? 9 : 0;
        for (unsigned int k = 0; k < width; k++) d[j * 12 + at + k] = frame_grad[j * width + k];
    }
    float* out = grad_local + (size_t)frame * joints * 9;
    for (int j = (int)joints - 1; j >= 0; j--) {
        const float* dg = d + j * 12;
        const float* dp = dg + 9;
        int p = parents[j];
        if (p < 0) {
            for (int k = 0; k < 9; k++) out[j * 9 + k] = dg[k];
            continue;
        }
        const float* r = frame_local + j * 9;
        const float* gp = globals + p * 12;
        const float* oj = o + j * 3;
        float* dgp = d + p * 12;
        for (int row = 0; row < 3; row++) {
            for (int c = 0; c < 3; c++) {
                float to_parent =
                    dg[row * 3] * r[c * 3] + dg[row * 3 + 1] * r[c * 3 + 1] + dg[row * 3 + 2] * r[c * 3 + 2];
                dgp[row * 3 + c] += to_parent + dp[row] * oj[c];
            }
            dgp[9 + row] += dp[row];
        }
        for (int row = 0; row < 3; row++) {
            for (int c = 0; c < 3; c++) {
                out[j * 9 + row * 3 + c] =
                    gp[row] * dg[c] + gp[3 + row] * dg[3 + c] + gp[6 + row] * dg[6 + c];
            }
        }
    }
}

// [batch, joints, 3] to [batch, 3], summed over joints in order (the root's gradient).
extern "C" __global__ void fk_sum_over_joints_f32(const float* values, unsigned int batch,
                                                  unsigned int joints, float* out) {
    unsigned int at = blockIdx.x * blockDim.x + threadIdx.x;
    if (at >= batch * 3) return;
    unsigned int frame = at / 3, i = at % 3;
    float sum = 0.0f;
    for (unsigned int j = 0; j < joints; j++) sum += values[((size_t)frame * joints + j) * 3 + i];
    out[at] = sum;
}
