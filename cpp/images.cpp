// Images for the cxx bridge declared in src/io/bridge.rs: read_image and write_image, OpenImageIO
// (2.4) behind plain-data functions. Nothing OIIO-typed crosses the bridge; every error is a C++
// exception whose what() names the file and the reason. No OpenVDB here.

#include "volgrad/cpp/bridge.h"
#include "volgrad/cpp/internal.h"
#include "volgrad/src/io/bridge.rs.h"

#include <OpenImageIO/imageio.h>

#include <algorithm>
#include <cerrno>
#include <cstdint>
#include <filesystem>
#include <memory>
#include <string>
#include <system_error>
#include <vector>

namespace fs = std::filesystem;

namespace volgrad {
namespace {

OIIO::TypeDesc pixel_type_desc(const std::string& t) {
    if (t == "half") return OIIO::TypeDesc::HALF;
    if (t == "float") return OIIO::TypeDesc::FLOAT;
    if (t == "uint8") return OIIO::TypeDesc::UINT8;
    fail("unknown pixel type '" + t + "' (expected half, float or uint8)");
}

// The first line of `text` that holds more than spaces.
std::string first_line(const std::string& text) {
    size_t start = 0;
    while (start < text.size()) {
        size_t end = text.find('\n', start);
        if (end == std::string::npos) end = text.size();
        if (text.find_first_not_of(" \r", start) < end) return text.substr(start, end - start);
        start = end + 1;
    }
    return "";
}

// OpenImageIO's message for a failure, on one line, or `silent` where it gives none (some readers
// fail on a truncated file without a word). A reader may stack several lines, each layer restating
// the last ("Read error: hit end of file", "PNG read error: IDAT: Read error: hit end of file",
// "PNG library error"): a line another line already contains is left out, the rest joined by "; ".
std::string oiio_error(const std::string& specific,
                       const std::string& silent = "unknown OpenImageIO error") {
    const std::string all = specific.empty() ? OIIO::geterror() : specific;
    std::vector<std::string> lines;
    size_t start = 0;
    while (start <= all.size()) {
        size_t end = all.find('\n', start);
        if (end == std::string::npos) end = all.size();
        std::string line = all.substr(start, end - start);
        while (!line.empty() && (line.back() == ' ' || line.back() == '\r')) line.pop_back();
        if (!line.empty()) lines.push_back(line);
        start = end + 1;
    }
    std::string e;
    for (size_t i = 0; i < lines.size(); ++i) {
        // Restated: inside a longer line, or the same as an earlier one (the first copy is kept).
        bool restated = false;
        for (size_t j = 0; j < lines.size(); ++j) {
            restated |= j != i && lines[j].find(lines[i]) != std::string::npos &&
                        (lines[j] != lines[i] || j < i);
        }
        if (restated) continue;
        if (!e.empty()) e += "; ";
        e += lines[i];
    }
    return e.empty() ? silent : e;
}

// An image file opened for reading (colour as stored: no (un)premultiplication of alpha), its
// header checked.
std::unique_ptr<OIIO::ImageInput> open_image(const std::string& path) {
    check_readable(path);
    OIIO::ImageSpec config;
    config.attribute("oiio:UnassociatedAlpha", 1);
    auto in = OIIO::ImageInput::open(path, &config);
    if (!in) fail("cannot read image " + quoted(path) + ": " + oiio_error(""));
    const OIIO::ImageSpec& spec = in->spec();
    if (spec.width <= 0 || spec.height <= 0 || spec.nchannels <= 0 || spec.depth > 1) {
        fail("cannot read image " + quoted(path) + ": unsupported size " +
             std::to_string(spec.width) + "x" + std::to_string(spec.height) + "x" +
             std::to_string(spec.depth) + " with " + std::to_string(spec.nchannels) + " channels");
    }
    return in;
}

// The image a file holds: an EXR's display window, whose stored data window may differ (a
// bounding box smaller than the frame, overscan beyond it) and is placed on it, the pixels it
// leaves out black and transparent (OpenEXR's rule); any other format's stored pixels, whatever
// offset it records (a PNG's oFFs says nothing of a frame).
struct Layout {
    int64_t width, height;
    bool whole;  // the stored pixels are the image
};

Layout layout_of(const OIIO::ImageInput& in) {
    const OIIO::ImageSpec& spec = in.spec();
    if (std::string(in.format_name()) != "openexr" || spec.full_width <= 0 ||
        spec.full_height <= 0) {
        return {spec.width, spec.height, true};
    }
    const bool whole = spec.x == spec.full_x && spec.y == spec.full_y &&
                       spec.width == spec.full_width && spec.height == spec.full_height;
    return {spec.full_width, spec.full_height, whole};
}

// A file of several images (an EXR's parts, a TIFF's pages, a GIF's frames) does not say which
// is the picture: reading the first would fit whatever it holds (a black utility part). Asked of
// a reader of its own, which is then closed: after a failed seek some readers are left unfit to
// read the first image (OpenImageIO 2.4's GIF reader then crashes in read_image).
void refuse_several_images(const std::string& path) {
    if (open_image(path)->seek_subimage(1, 0)) {
        fail("cannot read image " + quoted(path) +
             ": it holds several images (parts, pages or frames) and volgrad reads one: save the "
             "picture alone");
    }
}

// An EXR's 32-bit unsigned channels hold ids or counts, not radiance; read as colour they would
// come back divided by 2^32 - 1 (OpenImageIO's rule for integers), a picture near black.
void refuse_integer_colour(const OIIO::ImageInput& in, const std::string& path) {
    const OIIO::ImageSpec& spec = in.spec();
    if (std::string(in.format_name()) != "openexr") return;
    for (int c = 0; c < spec.nchannels; ++c) {
        const std::string& name = spec.channelnames[c];
        const size_t dot = name.rfind('.');
        const std::string last = dot == std::string::npos ? name : name.substr(dot + 1);
        const bool colour =
            last == "R" || last == "G" || last == "B" || last == "Y" || last == "A";
        if (colour && spec.channelformat(c).basetype == OIIO::TypeDesc::UINT) {
            fail("cannot read image " + quoted(path) + ": its channel " + name +
                 " holds 32-bit unsigned integers (an EXR's ids or counts), not radiance: store "
                 "colour as half or float");
        }
    }
}

}  // namespace

// ------------------------------------------------------------------------------------------------
// The bridge functions

ImageSize read_image_size(rust::Str path_str) {
    const std::string path = to_std(path_str);
    const Layout layout = layout_of(*open_image(path));
    return ImageSize{uint32_t(std::min<int64_t>(layout.width, UINT32_MAX)),
                     uint32_t(std::min<int64_t>(layout.height, UINT32_MAX))};
}

ImageData read_image(rust::Str path_str) {
    const std::string path = to_std(path_str);
    refuse_several_images(path);
    auto in = open_image(path);
    refuse_integer_colour(*in, path);
    const OIIO::ImageSpec& spec = in->spec();
    const auto [width, height, whole] = layout_of(*in);
    // The largest image the renderer makes (scene_check::MAX_PIXELS), and at most 4 GiB of
    // values: a header may declare far more than the file holds, and the buffers are allocated
    // before any pixel is read.
    const uint64_t max_pixels = uint64_t(1) << 28, max_values = uint64_t(1) << 30;
    const uint64_t pixels = uint64_t(width) * uint64_t(height);
    const uint64_t stored = uint64_t(spec.width) * uint64_t(spec.height);
    const uint64_t channels = uint64_t(spec.nchannels);
    if (pixels > max_pixels || stored > max_pixels ||
        (pixels + (whole ? 0 : stored)) * channels > max_values) {
        fail("cannot read image " + quoted(path) + ": it declares " + std::to_string(width) +
             "x" + std::to_string(height) + " pixels of " + std::to_string(spec.nchannels) +
             " channels (" + std::to_string(spec.width) + "x" + std::to_string(spec.height) +
             " stored), more than volgrad reads (2^28 pixels, 2^30 values)");
    }
    ImageData img;
    img.width = uint32_t(width);
    img.height = uint32_t(height);
    img.channels = uint32_t(spec.nchannels);
    img.color_space = std::string(spec.get_string_attribute("oiio:ColorSpace"));
    img.stored_type = std::string(spec.format.c_str());
    img.alpha_channel = spec.alpha_channel;
    img.alpha_unassociated = spec.get_int_attribute("oiio:UnassociatedAlpha") != 0;
    for (const std::string& name : spec.channelnames) img.channel_names.push_back(rust::String(name));
    // OpenEXR's primaries and white point (x, y of red, green, blue, white), when it states them.
    if (const OIIO::ParamValue* p = spec.find_attribute("chromaticities")) {
        if (p->type() == OIIO::TypeDesc(OIIO::TypeDesc::FLOAT, 8)) {
            const float* xy = static_cast<const float*>(p->data());
            for (int i = 0; i < 8; ++i) img.chromaticities.push_back(xy[i]);
        }
    }
    resize_f32s(img.pixels, size_t(width) * size_t(height) * size_t(channels));
    std::vector<float> window;
    if (!whole) window.resize(size_t(stored) * size_t(channels));
    float* into = whole ? img.pixels.data() : window.data();
    // A reader may fill what it could not decode and still report success, keeping the error for
    // whoever asks: a JPEG cut short or with damaged data comes back with its lower part grey, a
    // TIFF cut short with it black. Either is a picture the file does not hold.
    // The reader's own words follow, first line only: libtiff, for one, repeats its line for
    // every strip it could not read.
    if (!in->read_image(0, 0, 0, spec.nchannels, OIIO::TypeDesc::FLOAT, into) ||
        in->has_error()) {
        const std::string said = oiio_error(first_line(in->geterror()), "");
        fail("cannot read image " + quoted(path) +
             ": its pixels could not be read (is it cut short or damaged?)" +
             (said.empty() ? "" : " (" + said + ")"));
    }
    in->close();
    if (!whole) {
        // Row y of the data window is row y + spec.y − full_y of the image (x alike).
        for (int64_t row = 0; row < spec.height; ++row) {
            const int64_t y = row + spec.y - spec.full_y;
            const int64_t x0 = std::max<int64_t>(0, spec.full_x - spec.x);
            const int64_t x1 = std::min<int64_t>(spec.width, width + spec.full_x - spec.x);
            if (y < 0 || y >= height || x0 >= x1) continue;
            const float* from = window.data() + size_t(row * spec.width + x0) * channels;
            float* to = img.pixels.data() +
                        size_t(y * width + x0 + spec.x - spec.full_x) * channels;
            std::copy(from, from + size_t(x1 - x0) * channels, to);
        }
    }
    return img;
}

void write_image(rust::Str path_str, const ImageData& image, rust::Str pixel_type) {
    const std::string path = to_std(path_str);
    const std::string what = "cannot write image " + quoted(path);
    const OIIO::TypeDesc type = [&] {
        try {
            return pixel_type_desc(to_std(pixel_type));
        } catch (const BridgeError& e) {
            fail(what + ": " + e.what());
        }
    }();
    if (image.width == 0 || image.height == 0 || image.channels == 0) {
        fail(what + ": empty image (" + std::to_string(image.width) + "x" +
             std::to_string(image.height) + " with " + std::to_string(image.channels) +
             " channels)");
    }
    const size_t expected = size_t(image.width) * image.height * image.channels;
    if (image.pixels.size() != expected) {
        fail(what + ": " + std::to_string(image.pixels.size()) + " values for " +
             std::to_string(image.width) + "x" + std::to_string(image.height) + "x" +
             std::to_string(image.channels) + " (expected " + std::to_string(expected) + ")");
    }
    check_writable_target(path);
    const fs::path p(path);
    const std::string ext = p.extension().string();
    if (ext.empty()) fail(what + ": no file extension to choose the image format from");

    auto out = OIIO::ImageOutput::create(path);
    if (!out) fail(what + ": unknown image format '" + ext + "' (" + oiio_error("") + ")");
    OIIO::ImageSpec spec(int(image.width), int(image.height), int(image.channels), type);
    // The values are stored as given: no (un)premultiplication of alpha.
    spec.attribute("oiio:UnassociatedAlpha", 1);
    if (std::string(out->format_name()) == "openexr") spec.attribute("compression", "zip");

    // OIIO picks the format from the extension, so the temporary name keeps it.
    const fs::path tmp = temporary_beside(path, ext);
    auto cleanup = [&] {
        std::error_code ignored;
        fs::remove(tmp, ignored);
    };
    errno = 0;
    if (!out->open(tmp.string(), spec)) {
        // What the file system said of the temporary beside `path` (OIIO's message names the
        // temporary, with the system's words in its own form); OIIO's when it said nothing.
        const int err_no = errno;
        const std::string err = oiio_error(out->geterror());
        cleanup();
        const std::string folder = p.parent_path().empty() ? "." : p.parent_path().string();
        fail(what + ": cannot create a file in " + quoted(folder) + ": " +
             (err_no != 0 ? errno_text(err_no) : err));
    }
    const OIIO::TypeDesc stored = out->spec().format;  // what the format actually stores
    if (!out->write_image(OIIO::TypeDesc::FLOAT, image.pixels.data())) {
        const std::string err = oiio_error(out->geterror());
        out->close();
        cleanup();
        fail(what + ": " + err);
    }
    if (!out->close()) {
        const std::string err = oiio_error(out->geterror());
        cleanup();
        fail(what + ": " + err);
    }
    // Formats that cannot store the requested type silently fall back to another (PNG: uint8 for
    // "float"); that would lose precision the caller asked for, so it is an error. (Checked after
    // closing: closing an unwritten PNG makes libpng print to stderr.)
    if (stored != type) {
        cleanup();
        fail(what + ": the " + out->format_name() + " format cannot store " +
             to_std(pixel_type) + " pixels (it would store " + stored.c_str() + ")");
    }
    commit_file(tmp, path);
}

}  // namespace volgrad
