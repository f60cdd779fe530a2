"""The digests a run's output records of what it was made from."""

import hashlib

import numpy as np

from torchfit.provenance import file_digest, masks_digest, provenance


def test_file_digest_of_a_file_and_a_folder(tmp_path):
    a, b = tmp_path / "a.bin", tmp_path / "b.bin"
    a.write_bytes(b"frame one")
    b.write_bytes(b"frame two")
    assert file_digest(a) == hashlib.sha256(b"frame one").hexdigest()
    assert len(file_digest(a)) == 64 and file_digest(a) != file_digest(b)
    folder = file_digest(tmp_path)
    b.write_bytes(b"frame 2")  # one file's bytes change the folder's digest
    assert file_digest(tmp_path) != folder
    b.write_bytes(b"frame two")
    assert file_digest(tmp_path) == folder
    b.rename(tmp_path / "c.bin")  # so does a name
    assert file_digest(tmp_path) != folder
    assert file_digest(tmp_path / "missing") is None


def test_masks_digest_tells_one_pixel_and_the_shape():
    masks = np.zeros((3, 8, 10), bool)
    masks[1, 2:5, 3:7] = True
    same = masks.copy()
    assert masks_digest(masks) == masks_digest(same)
    same[2, 7, 9] = True
    assert masks_digest(masks) != masks_digest(same)
    assert masks_digest(masks) != masks_digest(masks.reshape(3, 10, 8))  # same bits, other frames


def test_provenance_names_the_libraries(tmp_path):
    import torch

    made = provenance(None, None)
    assert made["source"] is None and made["source_sha256"] is None and made["masks_sha256"] is None
    assert made["packages"]["torch"] == torch.__version__ and made["packages"]["numpy"] == np.__version__
    assert made["revision"] is None or isinstance(made["revision"], str)
    assert made["machine"]["torch_threads"] == torch.get_num_threads()
    assert made["machine"]["torch_cpu_capability"] == torch.backends.cpu.get_cpu_capability()
    assert isinstance(made["machine"]["cpu"], str) and made["machine"]["cpu"]


def test_provenance_records_the_variables_that_pick_the_math_kernels(monkeypatch):
    monkeypatch.setenv("MKL_CBWR", "COMPATIBLE")
    monkeypatch.delenv("ATEN_CPU_CAPABILITY", raising=False)
    env = provenance(None, None)["machine"]["numerics_env"]
    assert env["MKL_CBWR"] == "COMPATIBLE" and env["ATEN_CPU_CAPABILITY"] is None
