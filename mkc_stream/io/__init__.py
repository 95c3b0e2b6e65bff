"""File formats: the recording CSV (:mod:`mkc_stream.io.recording`) and loaders of public datasets
(:mod:`mkc_stream.io.datasets`)."""
from mkc_stream.io.recording import (
    Recording,
    RecordingError,
    bundled_recording,
    bundled_recording_path,
    bundled_recordings,
    read_recording,
    write_recording,
)
from mkc_stream.io.datasets import (
    load_broad,
    load_cave_survey_json,
    load_ck_explorer_csv,
    load_qmc5883l_csv,
    load_rasteiro_mat,
)

__all__ = [
    "Recording",
    "RecordingError",
    "bundled_recording",
    "bundled_recording_path",
    "bundled_recordings",
    "load_broad",
    "load_cave_survey_json",
    "load_ck_explorer_csv",
    "load_qmc5883l_csv",
    "load_rasteiro_mat",
    "read_recording",
    "write_recording",
]
