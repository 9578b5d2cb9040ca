"""An xarray backend: a store's level as a lazy, georeferenced DataArray of heights.

``xarray.open_dataset(store, engine="terrastream", level=L)`` returns a Dataset with one
variable, ``height`` (dims ``y, x``, metres, nodata and padding as NaN), backed by a dask
array with one chunk per store block (blocks are decoded only when a chunk is computed).
``x``/``y`` are the sample centres in the store's CRS; the CRS is a CF grid mapping variable
``spatial_ref`` (``crs_wkt`` and ``spatial_ref`` attributes, as rioxarray and GDAL read them).
``xarray.open_datatree(store, engine="terrastream")`` gives every level as a pyramid: groups
``level_0`` (coarsest) .. ``level_k`` (full resolution).

Level ``L`` keeps every ``2**(k-L)``-th sample of the DEM (rows and columns ``0, s, 2s, …``),
so its sample centres are a subset of the full-resolution ones: nothing is resampled.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Iterable
from typing import Any

import numpy as np
import xarray as xr
from xarray.backends import BackendArray, BackendEntrypoint
from xarray.core import indexing

from tiler.errors import StoreChangedError
from tiler.grid import as_index
from tiler.store import ATTR, TerrainStore, open_store

#: open stores by (URL, generation), and the one each URL opens to now: a dataset reads the
#: build it was opened on (a rewritten store raises for it), a new open reads the new build
_STORES: dict[tuple[str, str | None], TerrainStore] = {}
_LATEST: dict[str, TerrainStore] = {}
_STORES_LOCK = threading.Lock()
_NOW = object()  # (the store a URL opens to now)


def _new_stores_lock() -> None:
    """A forked child's own lock (the parent's may be held by a thread the child lacks; the
    cached stores reopen themselves there: ``TerrainStore._in_process``)."""
    global _STORES_LOCK
    _STORES_LOCK = threading.Lock()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_new_stores_lock)


def _cached_store(url: str, generation: str | None | object = _NOW) -> TerrainStore:
    """One open store per URL, build and process (TerrainStore is thread-safe, not
    picklable). Without ``generation``: the store the URL holds now (a cached one rewritten
    since, e.g. by ``tile --overwrite``, is opened anew); with it: that build's store, or
    :class:`StoreChangedError` if the URL holds another build now."""
    with _STORES_LOCK:
        if generation is _NOW:
            s = _LATEST.get(url)
            if s is not None:
                try:
                    s.check_unchanged(force=True)
                    return s
                except StoreChangedError:
                    pass  # rewritten: open the build it holds now
            s = open_store(url)
            _STORES[(url, s.meta.generation)] = _LATEST[url] = s
            return s
        s = _STORES.get((url, generation))  # type: ignore[arg-type]
        if s is None:  # (a dask worker process: open it, and check it is the same build)
            s = open_store(url)
            if s.meta.generation != generation:
                raise StoreChangedError(
                    f"store {url!r} was replaced or rewritten since this dataset was opened "
                    f"(generation {generation!r} -> {s.meta.generation!r}); open it again"
                )
            _STORES[(url, generation)] = s  # type: ignore[index]
        return s


def level_shape(store: TerrainStore, level: int) -> tuple[int, int, int]:
    """``(height, width, step)`` of a level's raster (every ``step``-th sample)."""
    step = 1 << (store.k - level)
    m = store.meta
    return (m.height - 1) // step + 1, (m.width - 1) // step + 1, step


def height_dtype(store: TerrainStore) -> np.dtype:
    """float32 when it holds the stored heights exactly (≤16-bit ints, float32), else float64."""
    dt = np.dtype(store.meta.dtype)
    if store.meta.extra.get("vertical") or dt.itemsize > 4 or (dt.kind in "iu" and dt.itemsize > 2):
        return np.dtype(np.float64)
    return np.dtype(np.float32)


def read_level_chunk(
    url: str, level: int, br: int, bc: int, generation: str | None | object = _NOW
) -> np.ndarray:
    """Chunk ``(br, bc)`` of a level: block ``(br, bc)`` without its shared last row/column
    (kept for the last block), nodata and padding as NaN; ``generation``: of the build read
    (default: the one the URL holds now)."""
    store = _cached_store(url, generation)
    h, w, step = level_shape(store, level)
    bstep = store.grid.step // step
    nr = min(bstep, h - br * bstep) if br < store.grid.rows - 1 else h - br * bstep
    nc = min(bstep, w - bc * bstep) if bc < store.grid.cols - 1 else w - bc * bstep
    dtype = height_dtype(store)
    if not store.index.exists[br, bc]:
        return np.full((nr, nc), np.nan, dtype=dtype)
    g = store.read_block((br, bc), level, extent=(nr, nc)).astype(dtype)
    valid = store.read_mask((br, bc))[::step, ::step][:nr, :nc]
    g[~valid] = np.nan
    return g


def _build(store: TerrainStore) -> str | None:
    """``store``'s generation, ``store`` kept as that build's (a dataset made from it reads
    it, not what its URL holds now: rewritten since, it raises StoreChangedError instead of
    giving the new build's heights under its own coordinates)."""
    with _STORES_LOCK:
        _STORES.setdefault((store.url, store.meta.generation), store)
    return store.meta.generation


def _chunks(n: int, bstep: int, nblocks: int) -> tuple[int, ...]:
    """Per-block chunk sizes along one axis: ``bstep`` each, the last block takes the rest."""
    return tuple(bstep if b < nblocks - 1 else n - b * bstep for b in range(nblocks))


class LevelArray(BackendArray):
    """Lazy ``(height, width)`` array of one level; reads only the blocks an index touches.

    Holds the store URL, not an open store, so it pickles (dask workers re-open the store).
    """

    def __init__(self, url: str, level: int, generation: str | None | object = _NOW) -> None:
        store = _cached_store(url, generation)
        self.url, self.level = url, level
        self.generation = store.meta.generation  # the build this array reads
        h, w, step = level_shape(store, level)
        self.shape = (h, w)
        self.dtype = height_dtype(store)
        self.bstep = store.grid.step // step
        self.blocks = store.grid.shape

    def __getitem__(self, key: indexing.ExplicitIndexer | tuple) -> np.ndarray:
        if isinstance(key, indexing.ExplicitIndexer):  # from xarray
            return indexing.explicit_indexing_adapter(
                key, self.shape, indexing.IndexingSupport.BASIC, self._getitem
            )
        return self._getitem(key)  # from dask.array.from_array: a tuple of slices

    def _getitem(self, key: tuple) -> np.ndarray:
        """Basic indexing (ints and slices): read the covering region, block by block."""
        key = tuple(key) + (slice(None),) * (2 - len(tuple(key)))
        idx = [np.arange(n)[k_] for k_, n in zip(key, self.shape, strict=True)]
        if any(np.size(i) == 0 for i in idx):
            return np.empty(tuple(np.size(i) for i in idx if np.ndim(i)), dtype=self.dtype)
        (r0, r1), (c0, c1) = ((int(np.min(i)), int(np.max(i)) + 1) for i in idx)
        region = np.full((r1 - r0, c1 - c0), np.nan, dtype=self.dtype)
        b = self.bstep
        rows, cols = self.blocks
        for br in range(min(r0 // b, rows - 1), min((r1 - 1) // b, rows - 1) + 1):
            for bc in range(min(c0 // b, cols - 1), min((c1 - 1) // b, cols - 1) + 1):
                chunk = read_level_chunk(self.url, self.level, br, bc, self.generation)
                cr0, cc0 = br * b, bc * b
                ir0, ir1 = max(r0, cr0), min(r1, cr0 + chunk.shape[0])
                ic0, ic1 = max(c0, cc0), min(c1, cc0 + chunk.shape[1])
                if ir0 < ir1 and ic0 < ic1:
                    region[ir0 - r0 : ir1 - r0, ic0 - c0 : ic1 - c0] = chunk[
                        ir0 - cr0 : ir1 - cr0, ic0 - cc0 : ic1 - cc0
                    ]
        out = region[np.asarray(idx[0]) - r0]  # int -> one row; array -> rows
        if np.ndim(idx[0]) == 0:
            return out[np.asarray(idx[1]) - c0]
        return out[:, np.asarray(idx[1]) - c0]


def level_dataarray(store: TerrainStore, level: int | None = None) -> xr.DataArray:
    """Level ``level`` (default finest) of ``store`` as a lazy georeferenced DataArray
    (dask-chunked one chunk per block)."""
    import dask.array as da
    from dask.base import tokenize

    k = store.k
    level = k if level is None else as_index(level, "level")
    if not 0 <= level <= k:
        from tiler.errors import StoreError

        raise StoreError(f"level must be in 0..{k} for {store.url!r}, got {level}")
    var = level_variable(store, level)
    arr = LevelArray(store.url, level, _build(store))
    build = (store.meta.generation, store.meta.source.get("checksum"))
    name = f"terrastream-{tokenize(store.url, level, *build)}"
    chunks = tuple(var.encoding["preferred_chunks"].values())
    data = da.from_array(arr, chunks=chunks, name=name, meta=np.empty((0, 0), arr.dtype))
    return xr.DataArray(
        xr.Variable(var.dims, data, var.attrs), coords=level_coords(store, level), name="height"
    )


def level_variable(store: TerrainStore, level: int) -> xr.Variable:
    """The lazily indexed ``height`` variable of a level (what the backend hands xarray)."""
    h, w, step = level_shape(store, level)
    bstep = store.grid.step // step
    rows, cols = store.grid.shape
    m = store.meta
    attrs = {
        "long_name": "height",
        "units": "m" if m.extra.get("vertical") else (m.vertical_units or "m"),
        "level": level,
        "levels": store.k + 1,
        "step": step,
    }
    if m.crs_wkt:
        attrs["grid_mapping"] = "spatial_ref"
    data = indexing.LazilyIndexedArray(LevelArray(store.url, level, _build(store)))
    var = xr.Variable(("y", "x"), data, attrs)
    var.encoding["preferred_chunks"] = {"y": _chunks(h, bstep, rows), "x": _chunks(w, bstep, cols)}
    var.encoding["_FillValue"] = np.nan  # nodata and padding are NaN (rioxarray's rio.nodata)
    return var


def level_coords(store: TerrainStore, level: int) -> dict[str, Any]:
    """``x``, ``y`` (sample centres) and the ``spatial_ref`` grid mapping of a level."""
    h, w, step = level_shape(store, level)
    g = store.grid
    geographic = _is_geographic(store.meta.crs_wkt)
    coords: dict[str, Any] = {
        "x": ("x", g.x0 + np.arange(w) * step * g.dx, _axis_attrs("x", geographic)),
        "y": ("y", g.y0 - np.arange(h) * step * g.dy, _axis_attrs("y", geographic)),
    }
    if store.meta.crs_wkt:
        coords["spatial_ref"] = ((), np.int64(0), grid_mapping_attrs(store, step))
    return coords


def _is_geographic(wkt: str | None) -> bool:
    from tiler.crs import is_geographic

    return is_geographic(wkt)


def _axis_attrs(axis: str, geographic: bool) -> dict[str, str]:
    if geographic:
        return (
            {"standard_name": "longitude", "units": "degrees_east", "axis": "X"}
            if axis == "x"
            else {"standard_name": "latitude", "units": "degrees_north", "axis": "Y"}
        )
    return {"standard_name": f"projection_{axis}_coordinate", "units": "m", "axis": axis.upper()}


def grid_mapping_attrs(store: TerrainStore, step: int = 1) -> dict[str, Any]:
    """CF grid-mapping attributes of the store's CRS, plus GDAL's ``GeoTransform`` (pixel
    corners, GDAL order) of a level with sample spacing ``step``."""
    import pyproj

    wkt = store.meta.crs_wkt
    attrs = dict(pyproj.CRS.from_wkt(wkt).to_cf())
    attrs["spatial_ref"] = wkt
    g = store.grid
    dx, dy = g.dx * step, g.dy * step
    attrs["GeoTransform"] = " ".join(
        repr(float(v)) for v in (g.x0 - dx / 2, dx, 0.0, g.y0 + dy / 2, 0.0, -dy)
    )
    return attrs


def level_dataset(store: TerrainStore, level: int | None = None, lazy: bool = False) -> xr.Dataset:
    """A Dataset holding a level's ``height`` and the store's description as attributes:
    dask-chunked per block, or (``lazy=True``, what the backend returns) lazily indexed."""
    level = store.k if level is None else as_index(level, "level")
    if lazy:
        if not 0 <= level <= store.k:
            from tiler.errors import StoreError

            raise StoreError(f"level must be in 0..{store.k} for {store.url!r}, got {level}")
        ds = xr.Dataset({"height": level_variable(store, level)}, coords=level_coords(store, level))
    else:
        ds = level_dataarray(store, level).to_dataset(promote_attrs=False)
    m = store.meta
    return ds.assign_attrs(
        {
            "title": f"terrastream store {m.source.get('name')}",
            # (a mosaic's every source, as its title's "+ N more" says there are)
            "source": "; ".join(map(str, m.source.get("paths") or [m.source.get("path")])),
            "terrastream_format_version": m.format_version,
            "Conventions": "CF-1.8",
        }
    )


def _opened(filename_or_obj: Any) -> TerrainStore:
    """The store to read: an open ``TerrainStore`` itself (its build), else the one its path
    or URL holds now."""
    if isinstance(filename_or_obj, TerrainStore):
        return filename_or_obj
    return _cached_store(_url(filename_or_obj))


def _url(filename_or_obj: Any) -> str:
    if isinstance(filename_or_obj, TerrainStore):
        return filename_or_obj.url
    if isinstance(filename_or_obj, str | os.PathLike):
        text = os.fspath(filename_or_obj)  # (a local path absolute: one cache entry per store,
        return text if "://" in text else os.path.abspath(text)  # whatever the cwd since)
    raise TypeError(f"the terrastream engine opens a store path or URL, not {filename_or_obj!r}")


class TerrastreamBackendEntrypoint(BackendEntrypoint):
    """``engine="terrastream"``: open a terrastream store's level (``level=L``) or all levels."""

    description = "terrastream non-redundant level stores as lazy georeferenced heights"
    url = "https://github.com/terrastream/terrastream/blob/main/docs/FORMAT.md"
    open_dataset_parameters = ("filename_or_obj", "drop_variables", "level")
    supports_groups = True

    def open_dataset(  # type: ignore[override]
        self,
        filename_or_obj: Any,
        *,
        drop_variables: str | Iterable[str] | None = None,
        level: int | None = None,
    ) -> xr.Dataset:
        """The store's level ``level`` (default: the finest) as a Dataset."""
        ds = level_dataset(_opened(filename_or_obj), level, lazy=True)
        if drop_variables:
            ds = ds.drop_vars(drop_variables, errors="ignore")
        return ds

    def open_groups_as_dict(  # type: ignore[override]
        self, filename_or_obj: Any, *, drop_variables: str | Iterable[str] | None = None
    ) -> dict[str, xr.Dataset]:
        """Every level as a group ``/level_L``; the root holds the store's description."""
        store = _opened(filename_or_obj)
        groups = {"/": xr.Dataset(attrs=level_dataset(store, 0, lazy=True).attrs)}
        for level in range(store.k + 1):
            ds = level_dataset(store, level, lazy=True)
            if drop_variables:
                ds = ds.drop_vars(drop_variables, errors="ignore")
            groups[f"/level_{level}"] = ds
        return groups

    def open_datatree(  # type: ignore[override]
        self, filename_or_obj: Any, *, drop_variables: str | Iterable[str] | None = None
    ) -> xr.DataTree:
        """The multiscale pyramid: ``level_0`` (coarsest) .. ``level_k`` (full resolution)."""
        return xr.DataTree.from_dict(
            self.open_groups_as_dict(filename_or_obj, drop_variables=drop_variables)
        )

    def guess_can_open(self, filename_or_obj: Any) -> bool:
        """True for a local directory whose root ``zarr.json`` carries the terrastream attribute."""
        try:
            path = _url(filename_or_obj)
        except TypeError:
            return False
        meta = os.path.join(path, "zarr.json")
        if "://" in path or not os.path.isfile(meta):
            return False
        try:
            with open(meta, encoding="utf-8") as f:
                return f'"{ATTR}"' in f.read(1 << 20)
        except OSError:
            return False
