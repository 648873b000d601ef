"""Uploading finished bags to S3-compatible object storage: resumable, verified, in order.

A bag leaves the robot file by file, each once it is closed, ``metadata.yaml`` last: in the store a bag is
complete exactly when its ``metadata.yaml`` is there. What is to be uploaded, and how far each upload got (the
multipart upload id and the parts the server confirmed), is kept in a journal next to the bags
(:mod:`~baglib.upload.journal`), so an upload cut by a network drop, a server restart, SIGKILL or a power cut goes
on from its last confirmed part. Every file is verified against the local one before it may be deleted
(:mod:`~baglib.upload.transfer`). The client is botocore with the standard AWS credential chain
(:mod:`~baglib.upload.client`); the uploads run in a process of their own (:mod:`~baglib.upload.worker`), so they
never take the recorder's CPU time or GIL.

This layer sits beside ``baglib.tools``: it may use ``baglib.format`` and ``baglib.read``, nothing above.
"""
