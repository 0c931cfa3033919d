"""The cohort platform ``spinecohort serve``: filter, find, see and download models in the browser.

``data`` opens a results folder or a release bag read-only (``logic`` holds its pure functions);
``scene`` turns node coordinates into the tissue-coloured VTK scene that vtk.js draws in the browser;
``app`` is one user's page state and controllers, ``page`` its layout, ``labels`` the clinical names,
``guard`` the checks of what a browser may set; ``launcher`` serves one page process per browser session
behind one port.  Nothing the browser sends becomes a path: models are named by validated IDs only.
"""
