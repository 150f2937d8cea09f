"""Getting data in: images (OpenImageIO, rawpy; native dtype, raw mosaics with their CFA), dataset folders
with an optional ``manifest.csv`` (frames, capture dates, conditions, epochs), one-pass streaming stack
statistics (mean, variance, minimum, maximum per pixel), and the summaries behind ``forensics info``.
"""
from forensics.io.dataset import (
    Dataset,
    Frame,
    decimal_year,
    from_decimal_year,
    list_images,
    open_dataset,
    parse_captured,
    split_epochs,
    write_manifest,
)
from forensics.io.describe import DatasetSummary, summarize_dataset, summarize_file
from forensics.io.images import (
    IMAGE_EXTENSIONS,
    RAW_EXTENSIONS,
    ImageInfo,
    RawMosaic,
    bits_dtype,
    is_raw,
    read_image,
    read_info,
    read_raw,
    write_image,
)
from forensics.io.stack import StackAccumulator, StackStats, stack_stats

__all__ = [
    "Dataset", "Frame", "decimal_year", "from_decimal_year", "list_images", "open_dataset", "parse_captured",
    "split_epochs", "write_manifest",
    "DatasetSummary", "summarize_dataset", "summarize_file",
    "IMAGE_EXTENSIONS", "RAW_EXTENSIONS", "ImageInfo", "RawMosaic", "bits_dtype", "is_raw", "read_image",
    "read_info", "read_raw", "write_image",
    "StackAccumulator", "StackStats", "stack_stats",
]
