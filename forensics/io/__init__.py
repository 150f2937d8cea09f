"""Getting data in: images (OpenImageIO, rawpy; native dtype, raw mosaics with their CFA), dataset folders
with an optional ``manifest.csv`` (frames, capture dates, conditions, epochs; the manifest read strictly),
capture dates and their plausible range, one-pass streaming stack statistics (mean, variance, minimum,
maximum per pixel), whether a frame holds any content (constant, black or saturated frames), and the
summaries behind ``forensics info``.
"""
import lazy_loader as _lazy

# Public names load their module on first use (as in scikit-image), so that importing one module of
# this package does not import the whole domain.
__getattr__, __dir__, __all__ = _lazy.attach(
    __name__,
    submod_attrs={
        "content": ["MIN_EXPOSED", "FrameContent", "content_problem", "frame_content"],
        "dataset": ["Dataset", "Frame", "binning", "common_binning", "list_images", "nominal_temperature",
                    "open_dataset", "set_point", "split_epochs", "temperature_groups"],
        "dates": ["FIRST_YEAR", "LAST_YEAR", "decimal_year", "from_decimal_year", "parse_captured"],
        "manifest": ["ManifestRow", "read_manifest", "write_manifest"],
        "describe": ["DatasetSummary", "summarize_dataset", "summarize_file"],
        "images": [
            "IMAGE_EXTENSIONS", "RAW_EXTENSIONS", "ImageInfo", "RawMosaic", "bits_dtype", "is_raw", "read_image",
            "file_problem", "read_info", "read_raw", "require_regular_file", "write_image",
        ],
        "stack": ["StackAccumulator", "StackStats", "stack_paths", "stack_sets", "stack_stats"],
    },
)
