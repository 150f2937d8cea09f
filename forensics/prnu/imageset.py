"""An ordered set of images loaded one at a time, on demand: what fingerprints, the same-device protocol and
clustering read their images from (:class:`ImageSet`).
"""
from __future__ import annotations

import functools
import os
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from forensics._shared.errors import InputError, UsageError

__all__ = ["ImageSet"]


class ImageSet:
    """An ordered set of images that are loaded one at a time, on demand.

    Parameters
    ----------
    loaders : sequence of callables
        ``loaders[i]()`` returns image ``i`` as an array ((H, W) or (H, W, 3)).
    sources : sequence of str
        A name for each image (file path, or a label).
    name : str
        Name of the set (for messages and reports).

    Notes
    -----
    Build one with :meth:`of` from a dataset folder, a :class:`forensics.io.dataset.Dataset`
    or a sequence of arrays, paths, frames or zero-argument callables, or with
    :meth:`from_function` for images rendered on demand (simulations).

    Work items of the execution layer name images by their index in a set, and the set
    is the items' shared data: on worker processes or a Dask cluster its loaders must be
    picklable (paths, dataset frames, module-level functions; a set of arrays is copied
    to every worker).
    """

    def __init__(self, loaders: Sequence[Callable[[], np.ndarray]], sources: Sequence[str], name: str) -> None:
        if len(loaders) != len(sources):
            raise UsageError("ImageSet: one source name per loader is needed")
        self._loaders = list(loaders)
        self.sources = [str(s) for s in sources]
        self.name = str(name)

    def __len__(self) -> int:
        return len(self._loaders)

    def load(self, index: int) -> np.ndarray:
        """Image ``index`` (decoded or rendered now; not cached)."""
        try:
            image = self._loaders[index]()
        except InputError:
            raise
        except (OSError, ValueError) as exc:
            raise InputError(f"{self.sources[index]}: cannot read the image ({exc})") from exc
        return np.asarray(image)

    def subset(self, indices: Sequence[int], name: str | None = None) -> ImageSet:
        """The images at ``indices`` (nothing is loaded), e.g. to split one set into disjoint halves."""
        idx = [int(i) for i in indices]
        return ImageSet([self._loaders[i] for i in idx], [self.sources[i] for i in idx], name or self.name)

    @classmethod
    def from_function(cls, n: int, render: Callable[[int], np.ndarray], name: str,
                      sources: Sequence[str] | None = None) -> ImageSet:
        """``n`` images where image ``i`` is ``render(i)`` (must be deterministic in ``i``)."""
        if n < 0:
            raise UsageError(f"ImageSet.from_function: n={n} must be non-negative")
        names = list(sources) if sources is not None else [f"{name}[{i}]" for i in range(n)]
        return cls([functools.partial(render, i) for i in range(n)], names, name)

    @classmethod
    def of(cls, source: Any, name: str | None = None) -> ImageSet:
        """An :class:`ImageSet` from a folder, a Dataset, or a sequence of images.

        Parameters
        ----------
        source : ImageSet, str, PathLike, Dataset or sequence
            A dataset folder (opened with :func:`forensics.io.dataset.open_dataset`), a
            Dataset, or a sequence whose items are arrays, image paths, objects with
            ``load()`` (and ``path``) such as :class:`forensics.io.dataset.Frame`, or
            zero-argument callables returning an array.
        name : str, optional
            Name of the set (default: the folder, or 'set').

        Raises
        ------
        InputError
            If the folder is not a dataset.
        UsageError
            If ``source`` is none of the above (e.g. a generator: images are drawn
            at random and shared out by index, so the set must know how many there are).
        """
        from forensics.io.dataset import Dataset, open_dataset

        if isinstance(source, ImageSet):
            if name is not None:
                return cls(source._loaders, source.sources, name)
            return source
        if isinstance(source, (str, os.PathLike)):
            source = open_dataset(source)
        if isinstance(source, Dataset):
            frames = list(source.frames)
            return cls([f.load for f in frames], [str(f.path) for f in frames], name or source.root.name or str(source.root))
        if not (hasattr(source, "__len__") and hasattr(source, "__getitem__")) or isinstance(source, np.ndarray):
            raise UsageError(
                "an image set must be a dataset folder, a Dataset, or a sequence of images (arrays, paths, "
                "frames or callables); generators and single arrays are not accepted"
            )
        label = name or "set"
        loaders: list[Callable[[], np.ndarray]] = []
        sources: list[str] = []
        for i in range(len(source)):
            item = source[i]
            if isinstance(item, np.ndarray):
                loaders.append(functools.partial(np.asarray, item))
                sources.append(f"{label}[{i}]")
            elif isinstance(item, (str, os.PathLike)):
                from forensics.io.images import read_image

                loaders.append(functools.partial(read_image, Path(item)))
                sources.append(str(item))
            elif hasattr(item, "load"):
                loaders.append(item.load)
                sources.append(str(getattr(item, "path", f"{label}[{i}]")))
            elif callable(item):
                loaders.append(item)
                sources.append(f"{label}[{i}]")
            else:
                raise UsageError(f"{label}[{i}]: {type(item).__name__} is not an image, a path, a frame or a callable")
        return cls(loaders, sources, label)
