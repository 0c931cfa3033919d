"""The cohort platform ``spinecohort serve``: filter, find, see and download models in the browser.

``data`` opens a results folder or a release bag read-only and answers the platform's questions with the
package's own functions (query, export, personalize, SSM sampling); ``scene`` turns node coordinates into
the tissue-coloured VTK scene that vtk.js draws in the browser; ``app`` is the trame page and its
controllers.  Nothing the browser sends becomes a path: models are named by validated IDs only.
"""
