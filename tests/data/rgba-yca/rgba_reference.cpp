// Reads an OpenEXR file through the OpenEXR library's RgbaInputFile (which reconstructs RGB
// from luminance/chroma files, ImfRgbaYca) and writes its R, G, B as a NumPy .npy array of
// shape (H, W, 3), float16, row 0 at the top of the data window.
//
//   g++ -O2 -o rgba_reference rgba_reference.cpp $(pkg-config --cflags --libs OpenEXR)
//   ./rgba_reference in.exr out.npy
#include <ImfArray.h>
#include <ImfRgbaFile.h>

#include <cstdio>
#include <cstring>
#include <string>

int main(int argc, char **argv) {
    if (argc != 3) {
        std::fprintf(stderr, "usage: %s in.exr out.npy\n", argv[0]);
        return 2;
    }
    Imf::RgbaInputFile file(argv[1]);
    const Imath::Box2i dw = file.dataWindow();
    const int w = dw.max.x - dw.min.x + 1, h = dw.max.y - dw.min.y + 1;
    Imf::Array2D<Imf::Rgba> px(h, w);
    file.setFrameBuffer(&px[0][0] - dw.min.x - dw.min.y * w, 1, w);
    file.readPixels(dw.min.y, dw.max.y);

    std::string dict = "{'descr': '<f2', 'fortran_order': False, 'shape': (" + std::to_string(h) + ", " +
                       std::to_string(w) + ", 3), }";
    while ((10 + dict.size() + 1) % 64 != 0) dict += ' ';
    dict += '\n';
    FILE *out = std::fopen(argv[2], "wb");
    if (!out) return 1;
    const unsigned char magic[8] = {0x93, 'N', 'U', 'M', 'P', 'Y', 1, 0};
    std::fwrite(magic, 1, 8, out);
    const unsigned short len = (unsigned short)dict.size();
    std::fputc(len & 0xff, out);
    std::fputc(len >> 8, out);
    std::fwrite(dict.data(), 1, dict.size(), out);
    for (int y = 0; y < h; ++y)
        for (int x = 0; x < w; ++x) {
            const Imf::Rgba &p = px[y][x];
            const unsigned short v[3] = {p.r.bits(), p.g.bits(), p.b.bits()};
            std::fwrite(v, 2, 3, out);  // little-endian host
        }
    return std::fclose(out) == 0 ? 0 : 1;
}
