"""Merging recorded runs with demonstrations: LeRobot's ``merge_datasets``, with the run labels intact.

LeRobot's ``merge_datasets`` (and ``lerobot-edit-dataset --operation.type=merge``) rewrites the data files
through pandas, which stores a NaN float as a null. The run labels' uncertainty score is NaN where the
policy was not consulted (``record_run``); a null reads back as None, which ``lerobot-train``'s collate
refuses. :func:`merge_runs` merges and writes the nulls back as NaN (:func:`restore_nan`).
"""

from __future__ import annotations

import os
from pathlib import Path

from lerobot_suture.datasets.scheduling import normal_scheduling


def merge_runs(datasets: list, repo_id: str, output_dir: str | Path):
    """``datasets`` (``LeRobotDataset``s with equal features: runs, and demonstrations labelled by
    :func:`~lerobot_suture.surgeon.record_run.label_demonstrations`) merged into one at ``output_dir``,
    ready for ``lerobot-train``; returns it."""
    from lerobot.datasets.dataset_tools import merge_datasets
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from lerobot_suture.datasets.video import resolve_video_backend

    with normal_scheduling():  # joining the videos may start the encoder, which leaves the thread real-time
        merged = merge_datasets(datasets, repo_id, Path(output_dir))
    if restore_nan(output_dir):  # the loaded dataset read the files before the repair: load them again
        merged = LeRobotDataset(repo_id, root=output_dir, video_backend=resolve_video_backend())
    return merged


def restore_nan(root: Path) -> int:
    """Null floats in the data files at ``root`` written back as NaN, row groups and schema kept; returns how
    many values were restored."""
    import pyarrow as pa
    import pyarrow.compute as pc
    import pyarrow.parquet as pq

    restored = 0
    for path in sorted((Path(root) / "data").rglob("*.parquet")):
        source = pq.ParquetFile(path)
        floats = [
            f.name
            for f in source.schema_arrow
            if pa.types.is_floating(f.type) and f.name in _null_columns(source)
        ]
        if not floats:
            continue
        tmp = path.with_name(f".{path.name}.tmp")
        with pq.ParquetWriter(tmp, source.schema_arrow) as writer:
            for group in range(source.num_row_groups):
                table = source.read_row_group(group)
                for name in floats:
                    index = table.schema.get_field_index(name)
                    column = table.column(index)
                    restored += column.null_count
                    nan = pa.scalar(float("nan"), type=column.type)
                    table = table.set_column(index, table.schema.field(index), pc.fill_null(column, nan))
                writer.write_table(table)
        os.replace(tmp, path)
    return restored


def _null_columns(source) -> set[str]:
    """Columns with a null in some row group (from the file's statistics, or by reading them when absent)."""
    names = set()
    metadata = source.metadata
    for group in range(metadata.num_row_groups):
        for column in range(metadata.num_columns):
            chunk = metadata.row_group(group).column(column)
            stats = chunk.statistics
            if stats is None or not stats.has_null_count or stats.null_count:
                names.add(chunk.path_in_schema)
    return names
