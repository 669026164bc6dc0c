// FlowBSDF OSL: random numbers. Cycles gives OSL no sampler state. On camera rays u comes from
// where the sample lies in its pixel (placed by Cycles' stratified sequence: film_u), so a
// pixel's samples are stratified in u too; elsewhere u is hashed from the shading point and
// the incoming ray (P, I, the ray length and the bounce depth), which differ between any two
// samples that can reach the same pixel.

float unit_from_hash(int h)
{
    return ((h >> 8) & 16777215) / 16777216.0;
}

// The cumulative distribution of Cycles' pixel-filter offset o (pixels from the pixel
// centre), as scene/film.cpp's filter_table importance-samples it: box over the width (1 px:
// Cycles ignores the width of its box), Blackman-Harris over twice the width, a Gaussian of
// sigma width / 4 over three times it (measured: tests/test_cycles.py, film-stratified test).
float filter_cdf(int type, float width, float o)
{
    if (type == 1)
        return clamp(o / width + 0.5, 0.0, 1.0);
    if (type == 2) {
        float a = 2.0 * M_PI * clamp(o / (2.0 * width) + 0.5, 0.0, 1.0);
        return (0.35875 * a - 0.48829 * sin(a) + 0.14128 / 2.0 * sin(2.0 * a)
                - 0.01168 / 3.0 * sin(3.0 * a)) / (0.35875 * 2.0 * M_PI);
    }
    float half = 1.5 * width;
    return 0.5 + 0.5 * erf(clamp(o, -half, half) / (0.25 * width * M_SQRT2));
}

// Where a camera sample's position f in [0, 1) within its raster cell falls in the
// distribution of f over all samples (the filter's offsets wrapped into one cell): uniform.
float wrapped_filter_cdf(int type, float width, float f)
{
    int reach = int(ceil(width * 1.5)) + 1;
    float c = 0.0;
    for (int k = -reach; k <= reach; k++)
        c += filter_cdf(type, width, f - 0.5 + k) - filter_cdf(type, width, k - 0.5);
    return clamp(c, 0.0, 1.0);
}

// Camera rays: u from the sample's position in its pixel, which Cycles places by its
// stratified QMC sequence (through the pixel filter), so a pixel's samples are stratified in
// u as well. Cranley-Patterson rotated: per raster cell for the box filter (every sample of a
// pixel lands in the pixel's own cell), else per render (the Seed: wider filters spill
// samples into neighbouring cells); u is uniform for every sample either way, so the
// estimate stays unbiased. Returns 0 where the position is not a raster position.
int film_u(int type, float width, int seed, output float u0, output float u1)
{
    point r = transform("raster", P);
    float cx = floor(r[0]), cy = floor(r[1]);
    int cell = (type == 1) ? hash(point(cx, cy, 0.0)) : 0;
    int h = hash(cell ^ hash(seed));
    u0 = mod(wrapped_filter_cdf(type, width, r[0] - cx) + unit_from_hash(hash(h)), 1.0);
    u1 = mod(wrapped_filter_cdf(type, width, r[1] - cy) + unit_from_hash(hash(h ^ 1540483477)), 1.0);
    return u0 >= 0.0 && u0 <= 1.0 && u1 >= 0.0 && u1 <= 1.0;
}
